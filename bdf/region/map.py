"""A region's map: the posterior of its one field, queried at points and on grids.

:func:`compute_posterior` turns the region's evidence (:mod:`bdf.region.evidence`) into
the posterior at the spec's hyperparameters: fixed, or ("auto") the evidence maximum of
the data in force, its search started at the previous version's optimum.
:class:`RegionMap` answers queries from it: predictive mean and std, the modes of a
directional map, and ``known``.

Where the region has no data the field reverts to its prior, whose predictive variance
under "auto" is set by the region's evidence (on the scale of its velocities). ``known``
marks the points where the map can be trusted: the data within the kernel's reach weigh at
least :data:`bdf.posterior.KNOWN_WEIGHT` (their own density,
:meth:`bdf.posterior.Posterior.data_weight`, not the boxes of the tiles that hold them) and
the answer flies no faster than the traffic near its altitude (below); per class, the
weight says where a mode is only its prior.

Plausibility: a map is judged against the traffic it learnt from (:func:`plausibility`):
no mean, and no mode with a share of at least :data:`MODE_SHARE`, should fly faster
horizontally than :data:`PLAUSIBLE_FACTOR` times the fastest traffic near its altitude
(:func:`speed_bound`, from the rows' speed histogram the tiles keep, per 100 m of
altitude). Each map computed for a region records its worst ratio to that bound.

A computed posterior is derived data, stored beside its evidence so that it is computed
once for all processes (:func:`encode_posterior`, :func:`decode_posterior`).
"""

from __future__ import annotations

import io
import logging
import pickle
from dataclasses import dataclass

import numpy as np

from bdf.field import BayesianDynamicField
from bdf.posterior import Mixture, Modes, Posterior, known
from bdf.region.spec import RegionSpec
from bdf.sparse import NotPositiveDefinite
from bdf.statistics import ALT_BIN_M, SPEED_BIN_MPS, SectorEvidence, altitude_bins
from bdf.validation import as_headings

log = logging.getLogger(__name__)
#: the plausibility bound: this factor over the fastest traffic observed near an altitude
PLAUSIBLE_FACTOR = 1.1
#: "near": rows within this distance of the altitude (metres; by their 100 m altitude bin)
NEAR_ALTITUDE_M = 1000.0
#: "fastest": this quantile of the horizontal speeds of the rows near the altitude
FASTEST_QUANTILE = 0.999
#: modes with at least this share are judged (a mode of almost no traffic is its prior)
MODE_SHARE = 0.05
#: the judging grid: 1 km apart horizontally, 500 m vertically, at most this many per axis
JUDGE_CELLS = 160
JUDGE_STEP_M = (1000.0, 500.0)


def compute_posterior(
    spec: RegionSpec, evidence: SectorEvidence, start=None, *, stored: bool = True, settle: bool = True
) -> Posterior | Mixture:
    """The region's posterior of ``evidence`` (:func:`bdf.region.evidence.region_total`) at the spec's
    hyperparameters, variance density ready, factors dropped. "auto" is this
    evidence's maximum (``posterior.alpha``, ``posterior.beta``), its search started at
    ``start`` (ratios alpha / beta, (3,) or a row per class: the optimum of the
    region's previous version) and the same from any start; ``settle=False``: within a nat
    of it, where that is quicker (:func:`bdf.hyperparameters.fit_evidence`).

    Fixed values that do not factor on ``stored`` data (which must be served) are
    raised (alpha by powers of ten) to the least that factors, with a warning; on data
    not stored yet (a fit, before it is applied) they raise ``NotPositiveDefinite``.

    The posterior's ``speed_bound`` (:func:`speed_bound` of the evidence's speeds) and
    ``plausibility`` (:func:`plausibility`) are set."""
    post = _posterior(spec, evidence, start, stored, settle)
    post.speed_bound = speed_bound(spec, evidence.speeds)
    post.plausibility = plausibility(RegionMap(spec, post))
    return post


#: what a stored posterior may name besides this package's classes (:func:`decode_posterior`):
#: numpy's arrays, dtypes and scalars, plain containers, and the stencil cache (a stencil is
#: pickled as its key)
POSTERIOR_NAMES = frozenset(
    {
        ("bdf.sparse.stencil", "lattice_stencil"),
        ("numpy", "dtype"),
        ("numpy", "ndarray"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy._core.numeric", "_frombuffer"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy.core.numeric", "_frombuffer"),
        ("collections", "OrderedDict"),
        ("builtins", "slice"),
        ("builtins", "frozenset"),
        ("builtins", "set"),
    }
)


#: The model a stored posterior was computed by: raised whenever a change of the model
#: changes the map the same evidence gives, or of what a stored map holds (2: a mode's local
#: prior mean; 3: its query tables as :class:`bdf.features.LaneTable`, 2026-11-28; 4: their
#: chunks as wide as :func:`bdf.features.lanes_for` says; 5: a mode's variance widened by
#: its class's spread where its prior holds it, :data:`bdf.posterior.CLASS_SPREAD_SHARE`;
#: 6: that spread about the mode's prior mean; all 2026-11-28; 7: local noise moments as a
#: :class:`bdf.features.LaneTable`, 2026-11-28), so that a map stored by an older code is
#: computed again, not served (:func:`decode_posterior`)
MODEL_REVISION = 7


def encode_posterior(post: Posterior | Mixture) -> bytes:
    """A computed (compact) posterior as bytes: :data:`MODEL_REVISION`, then its arrays and
    the objects that hold them."""
    return pickle.dumps((MODEL_REVISION, post), protocol=5)


def decode_posterior(blob: bytes) -> Posterior | Mixture:
    """:func:`encode_posterior`'s bytes back, naming only classes of this package and numpy's
    arrays (a damaged or foreign blob, or one of another :data:`MODEL_REVISION`, is a
    ``ValueError``, never code run)."""

    class Reader(pickle.Unpickler):
        def find_class(self, module: str, name: str):
            found = super().find_class(module, name) if module.startswith("bdf.") else None
            if not (isinstance(found, type) or (module, name) in POSTERIOR_NAMES):
                raise pickle.UnpicklingError(f"a stored posterior names {module}.{name}")
            return found or super().find_class(module, name)

    try:
        stored = Reader(io.BytesIO(blob)).load()
    except Exception as exc:
        raise ValueError(f"not a stored posterior: {exc}") from exc
    revision, post = stored if isinstance(stored, tuple) and len(stored) == 2 else (None, stored)
    if not isinstance(post, Posterior | Mixture):
        raise ValueError(f"not a stored posterior: a {type(post).__name__}")
    if revision != MODEL_REVISION:
        raise ValueError(f"a posterior of model revision {revision}, not this code's {MODEL_REVISION}")
    return post


def _posterior(spec: RegionSpec, evidence: SectorEvidence, start, stored: bool, settle: bool):
    """:func:`compute_posterior` but its judgement."""
    try:
        return region_field(spec).set_evidence(evidence, start=start, settle=settle).posterior_.compact()
    except NotPositiveDefinite:
        if spec.alpha == "auto" or not stored:
            raise
    # the spec's fixed alpha does not factor on stored (accepted) data, which must still
    # be served: at the least alpha ten times larger, a hundred, ... that does
    for power in range(1, 13):
        try:
            field = region_field(spec, np.asarray(spec.alpha, float) * 10.0**power)
            post = field.set_evidence(evidence, start=start, settle=settle).posterior_.compact()
        except NotPositiveDefinite:
            continue
        log.warning("region %s: served at alpha x 1e%d: its fixed alpha does not factor", spec.name, power)
        return post
    raise NotPositiveDefinite(f"region {spec.name}: no alpha up to 1e12 times the spec's factors")


@dataclass(frozen=True)
class SpeedBound:
    """The plausibility bound (m/s) as a function of altitude: piecewise constant, ``values[i]``
    between ``breaks[i - 1]`` and ``breaks[i]``, ``at_breaks[i]`` at ``breaks[i]``
    (:func:`speed_bound`)."""

    breaks: np.ndarray
    values: np.ndarray
    at_breaks: np.ndarray

    def __call__(self, z) -> np.ndarray:
        z = np.asarray(z, float)
        i = np.searchsorted(self.breaks, z)
        on = self.breaks[np.minimum(i, len(self.breaks) - 1)] == z
        return np.where(on, self.at_breaks[np.minimum(i, len(self.breaks) - 1)], self.values[i])


def speed_bound(spec: RegionSpec, speeds: np.ndarray | None) -> SpeedBound:
    """The plausibility bound at each altitude: :data:`PLAUSIBLE_FACTOR` x the
    :data:`FASTEST_QUANTILE` of the horizontal speeds of the rows within
    :data:`NEAR_ALTITUDE_M` of it (by their altitude bin's centre, 100 m bins; the upper
    edge of their speed bin); the region envelope's horizontal speed where none is.
    ``speeds``: the region's histogram (:func:`bdf.region.evidence.speed_histogram`,
    summed), or None (tiles stored before it). The bins in reach change only where an
    altitude is that far from a bin's centre: the bound is constant between those breaks."""
    first, count = altitude_bins(spec.grid)
    centres = (first + np.arange(count) + 0.5) * ALT_BIN_M
    envelope = spec.envelope.max_horizontal_speed_mps
    breaks = np.unique(np.concatenate([centres - NEAR_ALTITUDE_M, centres + NEAR_ALTITUDE_M]))
    mids = np.concatenate([[breaks[0] - 1.0], (breaks[:-1] + breaks[1:]) / 2, [breaks[-1] + 1.0]])

    def at(alt: float) -> float:
        near = 0.0 if speeds is None else speeds[np.abs(centres - alt) <= NEAR_ALTITUDE_M].sum(axis=0)
        if np.sum(near) == 0:
            return envelope
        edge = np.searchsorted(np.cumsum(near), FASTEST_QUANTILE * np.sum(near)) + 1
        return PLAUSIBLE_FACTOR * edge * SPEED_BIN_MPS

    return SpeedBound(breaks, np.array([at(m) for m in mids]), np.array([at(b) for b in breaks]))


def plausibility(rmap: RegionMap) -> dict:
    """The map over its box against its posterior's ``speed_bound``: on a grid 1 km apart
    horizontally and 500 m vertically (coarser where an axis would have more than
    :data:`JUDGE_CELLS` cells, finer where it would have fewer than 2), the fastest
    horizontal speed of the mean and of each mode with a share of at least
    :data:`MODE_SHARE`; its worst ratio to the bound there and the share of voxels above it."""
    spec = rmap.spec
    extent = spec.upper - spec.lower
    finest = np.array([JUDGE_STEP_M[0], JUDGE_STEP_M[0], JUDGE_STEP_M[1]])
    step = np.maximum(np.minimum(finest, extent / 2), extent / JUDGE_CELLS)  # a small box: 2 cells
    axes = [np.arange(lo + h / 2, hi, h) for lo, hi, h in zip(spec.lower, spec.upper, step, strict=True)]
    if spec.one_class:
        mean, _, _ = rmap.predict_grid(axes)
        fastest = np.hypot(mean[..., 0], mean[..., 1])
    else:
        modes = rmap.predict_grid_modes(axes)
        mean, _, _ = rmap.predict_grid(axes, modes=modes)
        mode_speed = np.where(
            modes.share >= MODE_SHARE, np.hypot(modes.mean[..., 0], modes.mean[..., 1]), 0.0
        )
        fastest = np.maximum(np.hypot(mean[..., 0], mean[..., 1]), mode_speed.max(axis=-1))
    ratio = fastest / rmap.bound_at(axes[2])[None, None, :]
    return {
        "worst_ratio": float(ratio.max()),
        "implausible_share": float(np.mean(ratio > 1.0)),
        "grid_step_m": step.tolist(),
    }


def region_field(spec: RegionSpec, alpha=None, beta=None) -> BayesianDynamicField:
    """An (unfitted) field over the region's lattice with its model settings (``alpha``,
    ``beta``: other values than the spec's): the model a region's map is the posterior of."""
    return BayesianDynamicField(
        spec.lower,
        spec.upper,
        spec.spacing_m,
        spec.gamma,
        spec.alpha if alpha is None else alpha,
        spec.beta if beta is None else beta,
        noise_spacing=spec.noise_spacing_m,
        noise_prior=spec.noise_prior,
        cutoff=spec.cutoff,
        directions=spec.model_directions,
        slow_mps=spec.slow_mps,
    )


@dataclass(frozen=True)
class RegionMap:
    """A region's posterior (:func:`compute_posterior`) with the spec it answers for:
    points and grids are checked against the region once, here."""

    spec: RegionSpec
    posterior: Posterior | Mixture

    def predict(
        self, X, heading_deg=None, modes: Modes | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predictive mean (n, 3), std (n, 3) and ``known`` (n,) at ``X`` inside the region,
        from the region's posterior. ``heading_deg`` (one or (n,)): the mode of that
        heading (a region of one direction has one). ``modes``: :meth:`predict_modes` of
        the same points when the caller has them (the answer derives from them)."""
        X = self.spec.inside_points(X)
        if heading_deg is not None:
            heading_deg = as_headings(heading_deg, len(X))
        if modes is None and (heading_deg is None or self.spec.one_class):
            mean, std, weight = self.posterior.answer(X)  # without the modes' arrays
        else:
            modes = self.posterior.predict_modes(X) if modes is None else modes
            mean, std = modes.answer(self.spec.sectors, heading_deg)
            weight = modes.weight
        return mean, std, self._known(weight, mean, X[:, 2])

    def bound_at(self, z: np.ndarray) -> np.ndarray:
        """The plausibility bound (m/s) at altitudes ``z``: the posterior's ``speed_bound``,
        or the envelope's speed (a posterior without one)."""
        bound = self.posterior.speed_bound
        if bound is None:
            return np.full(np.shape(z), self.spec.envelope.max_horizontal_speed_mps)
        return bound(z)

    def _known(self, weight: np.ndarray, mean: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Where the answer can be trusted: data weigh at least
        :data:`bdf.posterior.KNOWN_WEIGHT` within the kernel's reach, and its mean flies no
        faster horizontally than the traffic near that altitude (:meth:`bound_at`)."""
        return known(weight) & (np.hypot(mean[..., 0], mean[..., 1]) <= self.bound_at(z))

    def predict_modes(self, X) -> Modes:
        """:class:`~bdf.posterior.Modes` at ``X`` inside the region: of the classes it
        answers (:meth:`_answered`)."""
        return self._answered(self.posterior.predict_modes(self.spec.inside_points(X)))

    def predict_grid(self, axes, modes: Modes | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`predict` on the grid ``axes[0] x axes[1] x axes[2]`` (inside the region):
        mean and std (nx, ny, nz, 3), known (nx, ny, nz); separable, so a few small
        contractions per axis. ``modes``: :meth:`predict_grid_modes` of the same grid when
        the caller has them (the answer derives from them)."""
        axes = self.spec.grid_axes(axes)
        if modes is None:
            mean, std, weight = self.posterior.answer_grid(axes)  # without the modes' arrays
        else:
            mean, std = modes.answer(self.spec.sectors)
            weight = modes.weight
        return mean, std, self._known(weight, mean, axes[2][None, None, :])

    def predict_grid_modes(self, axes) -> Modes:
        """:class:`~bdf.posterior.Modes` on the grid ``axes``, the grid's shape first."""
        return self._answered(self.posterior.predict_grid_modes(self.spec.grid_axes(axes)))

    def _answered(self, modes: Modes) -> Modes:
        """A region of one class whose model is a mixture answers its moments as one mode."""
        if self.spec.one_class and modes.share.shape[-1] > 1:
            return modes.as_one_class()
        return modes
