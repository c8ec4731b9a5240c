"""The cost of flying through the velocity map, from one voxel grid of mean and std.

A route's cost is ``∫ (1 + risk(x) + flow(x, direction)) ds`` along it (metres):

* ``risk``: ``w_risk * s(x) / max_std_mps`` where ``s`` is the largest of the three
  predictive stds (the tube holds the points where ``s < max_std_mps``; the hard tube
  tests an upper bound of ``s`` between grid nodes, :meth:`CostMap.max_std_high`), or, with
  ``risk="exceedance"``, ``w_risk * P(some component deviates from the mean by more
  than margin_mps)`` under the Gaussian predictive; with a soft tube, plus
  ``w_tube * max(0, s / max_std_mps - 1)``.
* ``flow``: ``w_flow * c(x) * |cruise * direction - mean(x)| / cruise``, the mismatch
  between the vehicle's velocity and the local mean flow, weighted by the confidence
  ``c = b^2 / (b^2 + s^2)`` (``b = max_std_mps``): where the map knows nothing, the
  mean (the prior, 0) is not held against the route.

On a directional map (``modes``: each traffic class's share, mean and std, the classes of
:class:`bdf.sectors.Sectors`) a segment flies in the mode of its heading, the two nearest
sectors' modes pooled as the service answers a heading (:func:`bdf.sectors.heading_mode`; the
slow class when its horizontal speed at ``cruise_mps`` is below ``slow_mps``): risk, tube
and flow are that mode's, and a *conflict* term is added, ``w_conflict * sum over the
other classes c of share_c * c_c * |cruise * direction - mean_c| / cruise`` (the two pooled
counted by their weights): the traffic met there, weighted by its closing speed and by how
well the map knows it. (Swaminathan et al.'s "Down the CLiFF" cost weighs each mode's share by a
Mahalanobis distance of the planned velocity; here every term carries the map's epistemic
std.) A state (a point, no heading) is in the tube when some class's mode is.

Every term is at least 0, so the cost is at least the length: the straight-line length is
an admissible heuristic for OMPL's informed planners. Per-voxel fields are computed once
and interpolated trilinearly, vectorised over all samples of all segments; a segment is
sampled every ``sample_m`` (half the smallest grid step by default).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.special import erfc

from bdf.sectors import CROSSING_DEG, MIN_SHARE, Sectors, heading_mode

#: Where no tile has data, the std is at least this many tube bounds.
UNKNOWN_STD_RATIO = 10.0
#: Second differences at a cell's corners underestimate the curvature inside it (by ~10 %
#: for a field sampled 10 times per period): the hard tube's bound takes this much more.
CURVATURE_SAFETY = 1.25
#: Columns of the per-voxel field table.
S, RISK, CONFIDENCE, MEAN = 0, 1, 2, slice(3, 6)
#: Columns of the class table: the 6 fields above, then the class's share, std (e, n, u)
#: and the noise variance within it that a known heading narrows (:func:`bdf.sectors.heading_mode`).
SHARE, STD, HEADING_NOISE, CLASS_COLUMNS = 6, slice(7, 10), slice(10, 13), 13


@dataclass(frozen=True)
class CostWeights:
    """How a route is scored (see the module docstring)."""

    max_std_mps: float
    risk: float = 1.0
    flow: float = 0.5
    cruise_mps: float = 30.0
    tube: Literal["hard", "soft", "off"] = "hard"
    tube_penalty: float = 10.0
    risk_kind: Literal["std", "exceedance"] = "std"
    margin_mps: float = 5.0
    conflict: float = 3.0  # much less conflict exposure for a little length (bench/bench_planner.py)

    def __post_init__(self):
        for name in ("max_std_mps", "cruise_mps", "margin_mps"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("risk", "flow", "tube_penalty", "conflict"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"the weight {name} must not be negative, got {getattr(self, name)}")
        if self.tube not in ("hard", "soft", "off"):
            raise ValueError(f"tube must be 'hard', 'soft' or 'off', got {self.tube!r}")
        if self.risk_kind not in ("std", "exceedance"):
            raise ValueError(f"risk_kind must be 'std' or 'exceedance', got {self.risk_kind!r}")


@dataclass(frozen=True)
class ModeGrids:
    """A directional map on the grid: ``share`` (nx, ny, nz, C), ``mean``, ``std`` and
    ``heading_noise`` (nx, ny, nz, C, 3) of each traffic class of ``sectors`` (the service's
    grid with ``modes``; :class:`bdf.posterior.Modes`)."""

    share: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    heading_noise: np.ndarray
    sectors: Sectors


@dataclass(frozen=True)
class CostMap:
    """Trilinear cost fields on the grid ``axes`` (each increasing, evenly spaced).

    ``mean`` and ``std`` are (nx, ny, nz, 3) m/s, as the service's grid endpoint gives them.
    Where ``known`` is False no tile has data and the std is only the prior's: those voxels
    count as at least ``UNKNOWN_STD_RATIO`` tube bounds uncertain, and their mean as 0.
    """

    axes: tuple[np.ndarray, np.ndarray, np.ndarray]
    mean: np.ndarray
    std: np.ndarray
    weights: CostWeights
    known: np.ndarray | None = None
    sample_m: float | None = None
    modes: ModeGrids | None = None
    table: np.ndarray = field(init=False, repr=False)  # (nx * ny * nz, 6) per-voxel fields
    curvature: np.ndarray = field(init=False, repr=False)  # (cells, 3) of s, see max_std_high
    classes: np.ndarray | None = field(init=False, repr=False)  # (nx * ny * nz, C * 10) per class
    class_curvature: np.ndarray | None = field(init=False, repr=False)  # (cells, C, 3)

    def __post_init__(self):
        axes = tuple(np.asarray(a, float) for a in self.axes)
        shape = tuple(len(a) for a in axes)
        if len(axes) != 3 or min(shape) < 2:
            raise ValueError(f"the grid needs three axes of at least 2 values, got sizes {shape}")
        for d, a in enumerate(axes):
            steps = np.diff(a)
            if not (steps > 0).all() or not np.allclose(steps, steps[0], rtol=1e-9):
                raise ValueError(f"grid axis {d} must be evenly spaced and increasing")
        mean, std = np.asarray(self.mean, float), np.asarray(self.std, float)
        if mean.shape != (*shape, 3) or std.shape != (*shape, 3):
            raise ValueError(f"mean and std must have shape {(*shape, 3)}, got {mean.shape}, {std.shape}")
        if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std >= 0).all()):
            raise ValueError("mean and std must be finite and std non-negative")
        known = None
        if self.known is not None:
            known = np.asarray(self.known, bool)
            if known.shape != shape:
                raise ValueError(f"known must have shape {shape}, got {known.shape}")
        mean, std = self._unknown_as_prior(mean, std, known)
        object.__setattr__(self, "axes", axes)
        if self.sample_m is None:
            object.__setattr__(self, "sample_m", 0.5 * min(a[1] - a[0] for a in axes))
        if not self.sample_m > 0:
            raise ValueError(f"sample_m must be positive, got {self.sample_m}")
        table = _voxel_fields(mean, std, self.weights)
        classes = class_curvature = None
        if self.modes is not None:
            per_class = self._class_fields(shape, known)  # (nx, ny, nz, C, 13)
            # a state is in the tube when some class's mode with at least MIN_SHARE of the
            # traffic is: its fields are the least s's (the mixture's where no class has)
            s = np.where(per_class[..., SHARE] >= MIN_SHARE, per_class[..., S], np.inf)
            best = np.argmin(s, axis=-1)[..., None, None]
            chosen = np.take_along_axis(per_class, best, axis=-2)[..., 0, : CONFIDENCE + 1]
            flowing = np.isfinite(s).any(axis=-1)[..., None]
            table[..., : CONFIDENCE + 1] = np.where(flowing, chosen, table[..., : CONFIDENCE + 1])
            classes = per_class.reshape(-1, per_class.shape[-2] * per_class.shape[-1])
            class_curvature = np.stack(
                [_cell_curvature(per_class[..., c, S]) for c in range(per_class.shape[-2])], axis=-2
            ).reshape(-1, per_class.shape[-2], 3)
        object.__setattr__(self, "table", table.reshape(-1, 6))
        object.__setattr__(self, "curvature", _cell_curvature(table[..., S]).reshape(-1, 3))
        object.__setattr__(self, "classes", classes)
        object.__setattr__(self, "class_curvature", class_curvature)

    def _unknown_as_prior(self, mean, std, known):
        """Where no tile has data: std at least ``UNKNOWN_STD_RATIO`` bounds, mean 0."""
        if known is None:
            return mean, std
        floor = UNKNOWN_STD_RATIO * self.weights.max_std_mps
        k = known.reshape(*known.shape, *(1,) * (mean.ndim - known.ndim))
        return np.where(k, mean, 0.0), np.where(k, std, np.maximum(std, floor))

    def _class_fields(self, shape, known) -> np.ndarray:
        """(nx, ny, nz, C, 13): each class's fields (s, risk, confidence, mean), share, std and
        heading noise."""
        m = self.modes
        C = m.sectors.classes
        share = np.asarray(m.share, float)
        mean, std = np.asarray(m.mean, float), np.asarray(m.std, float)
        heading_noise = np.asarray(m.heading_noise, float)
        if share.shape != (*shape, C) or any(a.shape != (*shape, C, 3) for a in (mean, std, heading_noise)):
            raise ValueError(
                f"modes must have shapes {(*shape, C)} and {(*shape, C, 3)} for {C} classes, got "
                f"{share.shape}, {mean.shape}, {std.shape}, {heading_noise.shape}"
            )
        if not all(np.isfinite(a).all() for a in (mean, std, share, heading_noise)):
            raise ValueError("mode means, stds, heading noises and shares must be finite")
        # at most the variance, to its rounding (std is the root of a sum the noise is part of)
        if not ((heading_noise >= 0).all() and (heading_noise <= std * std * (1 + 1e-12)).all()):
            raise ValueError("a mode's heading noise must lie between 0 and its variance std^2")
        mean, std = self._unknown_as_prior(mean, std, known)
        return np.concatenate(
            [_voxel_fields(mean, std, self.weights), share[..., None], std, heading_noise], axis=-1
        )

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(len(a) for a in self.axes)

    @property
    def lower(self) -> np.ndarray:
        return np.array([a[0] for a in self.axes])

    @property
    def upper(self) -> np.ndarray:
        return np.array([a[-1] for a in self.axes])

    @property
    def step(self) -> np.ndarray:
        return np.array([a[1] - a[0] for a in self.axes])

    def fields(self, X) -> np.ndarray:
        """(n, 6) interpolated per-voxel fields: s, risk, confidence, mean e/n/u.

        Points outside the grid take the value at the nearest face (the planner's space is
        the grid's box, so this only matters for callers probing outside it).
        """
        return self._interpolate(X)[0]

    def _interpolate(self, X, table=None):
        """Fields at ``X`` (of ``table``, default the per-voxel fields), and each point's cell
        (flat index) and position in it (0..1)."""
        X = np.asarray(X, float).reshape(-1, 3)
        lower, inv_step, top, offsets, cell_strides = self._lookup
        u = (X - lower) * inv_step
        base = np.minimum(np.maximum(u.astype(np.int64), 0), top)  # u >= 0 inside: int() floors
        f = np.minimum(np.maximum(u - base, 0.0), 1.0)
        c = np.stack([1.0 - f, f], axis=2)  # (n, axis, 0/1 end)
        # corner order: x bit, y bit, z bit
        weights = (c[:, 0, :, None, None] * c[:, 1, None, :, None] * c[:, 2, None, None, :]).reshape(-1, 8)
        corners = (self.table if table is None else table)[(base @ self._strides)[:, None] + offsets]
        return np.einsum("nk,nkf->nf", weights, corners), base @ cell_strides, f

    @functools.cached_property
    def _strides(self) -> np.ndarray:
        _, ny, nz = self.shape
        return np.array([ny * nz, nz, 1])

    @functools.cached_property
    def _lookup(self):
        bits = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])
        top = np.array(self.shape) - 2
        cell_strides = np.array([(top[1] + 1) * (top[2] + 1), top[2] + 1, 1])
        return self.lower, 1.0 / self.step, top, bits @ self._strides, cell_strides

    def max_std(self, X) -> np.ndarray:
        """Interpolated ``s``: the largest of the three stds, m/s."""
        return self.fields(X)[:, S]

    def max_std_high(self, X) -> np.ndarray:
        """``s`` plus the bound of trilinear interpolation's error, what the hard tube tests:
        ``|s - I s| <= sum_d t_d (1 - t_d) / 2 * h_d^2 max |d^2 s / dx_d^2|`` in a cell
        (``t`` the position in it: 0 at the nodes, ``h^2 / 8`` times the curvature midway);
        only a concave ``s`` rises above its interpolation. Curvatures are estimated from
        the grid's second differences (:func:`_cell_curvature`), times ``CURVATURE_SAFETY``."""
        F, cell, t = self._interpolate(X)
        margin = np.einsum("nd,nd->n", t * (1.0 - t), self.curvature[cell])
        return F[:, S] + 0.5 * CURVATURE_SAFETY * margin

    def samples(self, P0, P1):
        """Sample points of segments ``P0[k] -> P1[k]``: (points, segment of each, its
        trapezoid weight in metres, lengths, direction per segment)."""
        P0, P1 = np.asarray(P0, float).reshape(-1, 3), np.asarray(P1, float).reshape(-1, 3)
        delta = P1 - P0
        length = np.linalg.norm(delta, axis=1)
        n = np.ceil(length / self.sample_m).astype(np.int64) + 1
        seg = np.repeat(np.arange(len(P0)), n)
        first = np.cumsum(n) - n
        t = (np.arange(n.sum()) - first[seg]) / np.maximum(n[seg] - 1, 1)
        # each sample stands for the stretch around it: n - 1 equal intervals, halves at the ends
        ds = (length / np.maximum(n - 1, 1))[seg]
        ds[first] *= 0.5
        ds[first + n - 1] *= 0.5
        direction = delta / np.maximum(length, 1e-300)[:, None]
        return P0[seg] + t[:, None] * delta[seg], seg, ds, length, direction

    def segment_costs(self, P0, P1) -> np.ndarray:
        """Cost of each segment ``P0[k] -> P1[k]`` (trapezoid rule on the samples), metres."""
        X, seg, ds, length, direction = self.samples(P0, P1)
        if self.modes is None:
            f = self.integrand(self.fields(X), direction[seg])
        else:
            f = self.flown(X, direction[seg])[0]
        return np.bincount(seg, weights=f * ds, minlength=len(length))

    def class_of(self, direction: np.ndarray) -> np.ndarray:
        """(n,) the traffic class of flying along unit ``direction`` (n, 3) at cruise speed."""
        return self.modes.sectors.classify(self.weights.cruise_mps * np.asarray(direction, float))

    def flown(self, X, direction) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """On a directional map, per sample flying along ``direction``: the cost per metre,
        the tube's s (upper bound, as :meth:`max_std_high`) of the mode flown, the class
        fields (n, C, 13) and the fields of the mode flown (n, 6). The mode flown is the
        heading's, its two nearest sectors' modes pooled (as the service's answer for a
        heading, :func:`bdf.sectors.heading_mode`), or the slow class's (:meth:`class_of`)."""
        w = self.weights
        F, cell, t = self._interpolate(X, self.classes)
        sectors = self.modes.sectors
        F = F.reshape(len(F), sectors.classes, CLASS_COLUMNS)
        n = np.arange(len(F))
        heading = np.degrees(np.arctan2(direction[:, 0], direction[:, 1]))
        k0, k1, weight = sectors.nearest_two(heading)
        slow = self.class_of(direction) == sectors.directions
        k0, k1 = np.where(slow, sectors.directions, k0), np.where(slow, sectors.directions, k1)
        weight = np.where(slow, 1.0, weight)
        mean, std = heading_mode(
            sectors, heading, weight, *(F[n, k, col] for k in (k0, k1) for col in (MEAN, STD, HEADING_NOISE))
        )
        # one class flown (the slow one, or a map of one direction): its fields as interpolated
        own = np.where((k0 == k1)[:, None], F[n, k0, :SHARE], _voxel_fields(mean, std, w))
        mean = own[:, MEAN]
        closing = np.linalg.norm(w.cruise_mps * direction[:, None, :] - F[:, :, MEAN], axis=2) / w.cruise_mps
        met = F[:, :, SHARE] * F[:, :, CONFIDENCE] * closing
        conflict = met.sum(axis=1) - weight * met[n, k0] - (1.0 - weight) * met[n, k1]
        flow = np.linalg.norm(w.cruise_mps * direction - mean, axis=1) / w.cruise_mps
        cost = 1.0 + own[:, RISK] + w.flow * own[:, CONFIDENCE] * flow + w.conflict * conflict
        bend = t * (1.0 - t)
        margin = np.maximum(
            np.einsum("nd,nd->n", bend, self.class_curvature[cell, k0]),
            np.einsum("nd,nd->n", bend, self.class_curvature[cell, k1]),
        )
        return cost, own[:, S] + 0.5 * CURVATURE_SAFETY * margin, F, own

    def integrand(self, F: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Cost per metre at samples with fields ``F`` flying along unit ``direction``."""
        w = self.weights
        mismatch = np.linalg.norm(w.cruise_mps * direction - F[:, MEAN], axis=1) / w.cruise_mps
        return 1.0 + F[:, RISK] + w.flow * F[:, CONFIDENCE] * mismatch

    def segment(self, a, b) -> tuple[float, bool]:
        """Cost of the one segment ``a -> b`` and whether it stays in the tube: what
        :meth:`segment_costs` and :meth:`segments_in_tube` give, from one interpolation and
        fewer array calls (the planner's callbacks ask one segment at a time)."""
        a = np.asarray(a, float)
        delta = np.asarray(b, float) - a
        length = math.sqrt(float(delta @ delta))
        n = math.ceil(length / self.sample_m) + 1
        if self.modes is not None:
            X = a + np.linspace(0.0, 1.0, n)[:, None] * delta
            direction = np.broadcast_to(delta / max(length, 1e-300), X.shape)
            f, s_high, *_ = self.flown(X, direction)
            cost = length / max(n - 1, 1) * (float(f.sum()) - 0.5 * float(f[0] + f[-1]))
            return cost, bool((s_high <= self.weights.max_std_mps).all())
        F, cell, t = self._interpolate(a + np.linspace(0.0, 1.0, n)[:, None] * delta)
        w = self.weights
        flow = w.cruise_mps * delta / max(length, 1e-300) - F[:, MEAN]
        f = (
            1.0
            + F[:, RISK]
            + (w.flow / w.cruise_mps) * F[:, CONFIDENCE] * np.sqrt(np.einsum("nc,nc->n", flow, flow))
        )
        cost = length / max(n - 1, 1) * (float(f.sum()) - 0.5 * float(f[0] + f[-1]))
        margin = np.einsum("nd,nd->n", t * (1.0 - t), self.curvature[cell])
        in_tube = bool((F[:, S] + 0.5 * CURVATURE_SAFETY * margin <= w.max_std_mps).all())
        return cost, in_tube

    def segments_in_tube(self, P0, P1) -> np.ndarray:
        """True per segment when every sample has ``s_high <= max_std_mps``: the true std
        between grid nodes can exceed the interpolated one, never ``s_high`` (up to the
        curvature estimate)."""
        X, seg, _, length, direction = self.samples(P0, P1)
        s_high = self.max_std_high(X)
        if self.modes is not None:  # a segment holds the mode flown; a state (no length) any mode
            moving = length[seg] > 0
            s_high[moving] = self.flown(X[moving], direction[seg][moving])[1]
        bad = s_high > self.weights.max_std_mps
        return np.bincount(seg, weights=bad, minlength=len(np.atleast_2d(P0))) == 0


def _voxel_fields(mean: np.ndarray, std: np.ndarray, w: CostWeights) -> np.ndarray:
    s = std.max(axis=-1)
    ratio = s / w.max_std_mps
    if w.risk_kind == "std":
        risk = w.risk * ratio
    else:
        with np.errstate(divide="ignore"):
            p_inside = 1.0 - erfc(w.margin_mps / (np.sqrt(2.0) * std))  # per component
        risk = w.risk * (1.0 - np.prod(p_inside, axis=-1))
    if w.tube == "soft":
        risk = risk + w.tube_penalty * np.maximum(ratio - 1.0, 0.0)
    confidence = 1.0 / (1.0 + ratio**2)
    return np.concatenate([s[..., None], risk[..., None], confidence[..., None], mean], axis=-1)


def _cell_curvature(s: np.ndarray) -> np.ndarray:
    """(nx-1, ny-1, nz-1, 3): per cell and axis ``d``, ``h_d^2 max(-d^2 s / dx_d^2, 0)``, the
    concave curvature of ``s``, from the second differences at the cell's 8 corners
    (extrapolated linearly to the grid's faces)."""
    out = np.zeros((*(n - 1 for n in s.shape), 3))
    for d in range(3):
        if s.shape[d] < 3:
            continue
        second = np.moveaxis(np.diff(s, n=2, axis=d), d, 0)
        if len(second) >= 2:  # linear extrapolation to the faces
            first, last = 2 * second[0] - second[1], 2 * second[-1] - second[-2]
        else:
            first, last = second[0], second[-1]
        node = np.moveaxis(np.concatenate([first[None], second, last[None]]), 0, d)
        out[..., d] = sliding_window_view(np.maximum(-node, 0.0), (2, 2, 2)).max(axis=(-3, -2, -1))
    return out


def path_metrics(costmap: CostMap, waypoints) -> dict[str, float]:
    """Length, flight time, std along the path, tube fraction, integrated risk, flow mismatch;
    on a directional map also the conflict exposure: the mean share, along the path, of
    traffic in sectors at least ``CROSSING_DEG`` off the heading flown (crossing or opposing),
    and the std, tube fraction and risk are those of the mode flown."""
    P = np.asarray(waypoints, float)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 2:
        raise ValueError(f"a path needs at least 2 waypoints of 3 coordinates, got shape {P.shape}")
    w = costmap.weights
    X, seg, ds, length, direction = costmap.samples(P[:-1], P[1:])
    total = float(length.sum())
    extra = {}
    if costmap.modes is None:
        F = costmap.fields(X)
    else:
        _, _, classes, F = costmap.flown(X, direction[seg])
        sectors = costmap.modes.sectors
        flown = np.degrees(np.arctan2(direction[seg, 0], direction[seg, 1]))
        off = np.abs((sectors.centres_deg[None, :] - flown[:, None] + 180.0) % 360.0 - 180.0)
        crossing = (classes[:, : sectors.directions, SHARE] * (off >= CROSSING_DEG)).sum(axis=1)
        extra["conflict_exposure"] = float((crossing * ds).sum() / max(total, 1e-300))
    s = F[:, S]
    mismatch = np.linalg.norm(w.cruise_mps * direction[seg] - F[:, MEAN], axis=1)
    return {
        "length_m": total,
        "flight_time_s": total / w.cruise_mps,
        "max_std_mps": float(s.max()),
        "mean_std_mps": float((s * ds).sum() / max(total, 1e-300)),
        "in_tube_fraction": float(((s <= w.max_std_mps) * ds).sum() / max(total, 1e-300)),
        "integrated_risk_m": float((F[:, RISK] * ds).sum()),
        "flow_mismatch_mps": float((F[:, CONFIDENCE] * mismatch * ds).sum() / max(total, 1e-300)),
        "cost_m": float(costmap.segment_costs(P[:-1], P[1:]).sum()),
        **extra,
    }
