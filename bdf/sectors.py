"""Traffic classes of a directional map: heading sectors and a slow class (DESIGN "Directions").

With ``directions = S > 1`` an observation's horizontal heading (degrees from north,
clockwise) puts it in one of S sectors of width 360/S centred on 0, 360/S, ...; below
``slow_mps`` of horizontal speed heading means nothing (hovering, climbing vertically)
and it goes to the slow class, the last. ``directions = 1`` is one class: every
observation, the paper's model.

Each observation goes to one class (hard assignment), so a class's evidence is exactly
that of the observations in it. Splitting each between the two nearest sector centres
(soft assignment, linear in angle) scores a worse mixture MSLL on the Paris flight split
and the same conditional RMSE (``bench/bench_core.py --directions 8 --soft 8``): hard it is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Largest number of heading sectors.
MAX_DIRECTIONS = 32
#: ``directions="auto"``: the heading resolutions cross-validated (:func:`bdf.crossval.cross_validate`,
#: a region's fit: :mod:`bdf.region.resolution`)
AUTO_DIRECTIONS = (8, 16, 24, 32)
#: A mode carrying less of the traffic than this is not a flow: tubes, pictures and the
#: planner ignore it (a near-empty class can look certain, e.g. the slow class fitted as
#: constant where it has no data).
MIN_SHARE = 0.05
#: A class at least this many degrees off the heading flown is crossing or opposing traffic
#: (the conflict exposure of a route: the planner's cost and :func:`bdf.region.route.assess`).
CROSSING_DEG = 67.5
#: Stds below this (m/s) are taken as it when modes are pooled (:func:`heading_mode`).
TINY_STD = 1e-9
#: A known heading narrows a mode's noise by at most this share in each component
#: (:func:`heading_mode`): the rest is scatter that no heading tells.
HEADING_NOISE_CAP = 0.9


@dataclass(frozen=True)
class Sectors:
    """The traffic classes of a map: ``directions`` heading sectors, then the slow class."""

    directions: int = 1
    slow_mps: float = 5.0

    def __post_init__(self):
        if not (isinstance(self.directions, int | np.integer) and 1 <= self.directions <= MAX_DIRECTIONS):
            raise ValueError(f"directions must be an integer in 1-{MAX_DIRECTIONS}, got {self.directions!r}")
        if not (np.isfinite(self.slow_mps) and self.slow_mps > 0):
            raise ValueError(f"slow_mps must be positive, got {self.slow_mps!r}")

    @property
    def classes(self) -> int:
        return 1 if self.directions == 1 else self.directions + 1

    @property
    def centres_deg(self) -> np.ndarray:
        """Heading of each sector's centre (degrees from north, clockwise)."""
        return np.arange(self.directions) * (360.0 / self.directions)

    def sector_of_heading(self, heading_deg) -> np.ndarray:
        """The sector holding each heading (degrees; any finite value, wrapped)."""
        h = np.asarray(heading_deg, float)
        if not np.all(np.isfinite(h)):
            raise ValueError("heading_deg must be finite")
        width = 360.0 / self.directions
        return np.floor(np.mod(h + width / 2.0, 360.0) / width).astype(np.int64) % self.directions

    def nearest_two(self, heading_deg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sectors whose centres enclose each heading (degrees; any finite value,
        wrapped), ``k0`` then ``k1`` clockwise, and ``k0``'s weight: linear in angle, 1 at
        ``k0``'s centre, 1/2 on the boundary, 0 at ``k1``'s centre (:func:`heading_mode`)."""
        h = np.asarray(heading_deg, float)
        if not np.all(np.isfinite(h)):
            raise ValueError("heading_deg must be finite")
        turns = np.mod(h, 360.0) / (360.0 / self.directions)
        k0 = np.floor(turns).astype(np.int64) % self.directions
        return k0, (k0 + 1) % self.directions, 1.0 - (turns - np.floor(turns))

    def classify(self, V: np.ndarray) -> np.ndarray:
        """(n,) class of each velocity (n, 3) (east, north, up)."""
        if self.directions == 1:
            return np.zeros(len(V), np.int64)
        heading = np.degrees(np.arctan2(V[:, 0], V[:, 1]))
        out = self.sector_of_heading(heading)
        out[np.hypot(V[:, 0], V[:, 1]) < self.slow_mps] = self.directions
        return out


def mixture_moments(share: np.ndarray, mean: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std per component (..., 3) of the mixture with weights ``share`` (..., C) of
    modes ``mean``, ``std`` (..., C, 3)."""
    m = np.einsum("...c,...cd->...d", share, mean)
    # sum_c share_c (std_c^2 + mean_c^2), without (..., C, 3) temporaries (grids are large)
    second = np.einsum("...c,...cd,...cd->...d", share, std, std) + np.einsum(
        "...c,...cd,...cd->...d", share, mean, mean
    )
    return m, np.sqrt(np.maximum(second - m * m, 0.0))


def heading_mode(
    sectors: Sectors, heading_deg, weight, mean0, std0, noise0, mean1, std1, noise1
) -> tuple[np.ndarray, np.ndarray]:
    """The mode of a heading between two sector centres (:meth:`Sectors.nearest_two`, whose
    ``weight`` is ``k0``'s): mean and std (..., 3) of modes ``k0`` and ``k1`` (mean, std, and
    the noise variance within std^2, each (..., 3)) pooled, their noise across the track
    narrowed by as much as the pool turns with the heading.

    The pool is log-linear, ``N(mean0, std0)^w N(mean1, std1)^(1 - w)`` per component: its
    precision is ``w / std0^2 + (1 - w) / std1^2`` and its mean the precision-weighted one:
    continuous in the heading, the sector's own mode's mean at its centre, and the better
    known of two modes counts for more. On the Paris flight split it beats the sector's own mode on
    conditional RMSE and MSLL at 8 to 32 sectors, and the linear blend of the two on MSLL and
    cov95 (``bench/bench_directions.py``).

    A mode's noise holds its class's spread across the track: flights of the sector's other
    headings. The heading given tells where in that spread a flight is, as far as the
    pooled mean follows the heading: it turns by ``kappa`` radians per radian of heading
    (``d atan2(e, n) / dh`` of the pool, clipped to [0, 1]), so a flight ``d`` off the mode
    misses the pool across the track by ``(1 - kappa) d``. So each mode's noise across the
    heading loses ``1 - (1 - kappa)^2`` of itself, but no more than the spread of headings
    the pool can tell apart (uniform between the two modes' directions, angle ``a``:
    ``|mean|^2 a^2 / 12`` across the track), and every component keeps at least
    ``1 - HEADING_NOISE_CAP`` of its noise, before the stds are pooled; the mean is the pool
    of the modes as they are. Where both modes hold traffic that points along their sectors
    the pool turns with the heading (``kappa`` near 1, ``a`` the sector's width); where the
    second mode is only its prior it does not; where one corridor fills both, ``a`` is small.
    On the Paris flight split at 16 sectors the conditional cov95 goes from 0.973 to 0.968
    and its MSLL from -1.938 to -1.947 (``bench/bench_directions.py``); along a corridor of
    drones crossing a sector boundary (a test's) cov95 goes from 0.951 to 0.930
    (``bench/history/heading-noise-rules.py``, with the rules tried before)."""
    w = np.asarray(weight, float)[..., None]
    a0 = 1.0 / np.maximum(std0, TINY_STD) ** 2
    a1 = 1.0 / np.maximum(std1, TINY_STD) ** 2
    precision = w * a0 + (1.0 - w) * a1
    mean = (w * a0 * mean0 + (1.0 - w) * a1 * mean1) / precision
    # d mean / d w per component; w falls by 1 over a sector's width as the heading turns
    turn_w = a0 * a1 * (mean0 - mean1) / precision**2
    e, n = mean[..., 0], mean[..., 1]
    horizontal_sq = e * e + n * n
    width = np.radians(360.0 / sectors.directions)
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = (e * turn_w[..., 1] - n * turn_w[..., 0]) / (width * horizontal_sq)
    kappa = np.clip(np.where(horizontal_sq > 0.0, kappa, 0.0), 0.0, 1.0)
    # the headings the pool can tell apart lie between the two modes' directions: their
    # spread across the track is at most that of headings uniform over that angle (none
    # where a mode stands still: it points nowhere)
    d0, d1 = (np.arctan2(m[..., 0], m[..., 1]) for m in (mean0, mean1))
    still = (mean0[..., :2] == 0.0).all(axis=-1) | (mean1[..., :2] == 0.0).all(axis=-1)
    between = np.where(still, 0.0, np.mod(d1 - d0 + np.pi, 2.0 * np.pi) - np.pi)
    spread = horizontal_sq * between**2 / 12.0
    h = np.radians(np.asarray(heading_deg, float))
    across_sq = np.stack(np.broadcast_arrays(np.cos(h) ** 2, np.sin(h) ** 2, 0.0), axis=-1)  # (..., 3)
    narrowed = []
    for std, noise in ((std0, noise0), (std1, noise1)):
        told = np.minimum((1.0 - (1.0 - kappa) ** 2) * np.sum(noise * across_sq, axis=-1), spread)
        cut = np.minimum(told[..., None] * across_sq, HEADING_NOISE_CAP * noise)
        narrowed.append(np.maximum(std, TINY_STD) ** 2 - cut)
    return mean, 1.0 / np.sqrt(w / narrowed[0] + (1.0 - w) / narrowed[1])
