"""The posterior of a field: what a factorisation of its evidence gives (paper III-A..E)."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numba
import numpy as np
from scipy import ndimage

from bdf import _blas, features, hyperparameters, noise, sparse
from bdf.features import LaneTable
from bdf.grid import HingeGrid
from bdf.kernel import Kernel
from bdf.sectors import Sectors, heading_mode, mixture_moments
from bdf.statistics import MIDPOINT_BLOCK, Evidence, SectorEvidence

#: ``known``: the data within the kernel's reach weigh at least this (:func:`known`): one
#: observation of weight 1 at the kernel's 1 % reach, or a track's unit of weight
#: (:func:`bdf.ingest.track_weights`) passing there.
KNOWN_WEIGHT = 0.01


def known(weight: np.ndarray) -> np.ndarray:
    """Where a map holds data: the data's weight within the kernel's reach (summed over the
    classes, the last axis of ``weight``: :meth:`Posterior.data_weight`) is at least
    :data:`KNOWN_WEIGHT`."""
    return weight.sum(axis=-1) >= KNOWN_WEIGHT


class Modes(NamedTuple):
    """A directional map at n points: per class (the heading sectors, then the slow class)."""

    share: np.ndarray  # (n, C) fraction of traffic, non-negative, summing to 1
    share_std: np.ndarray  # (n,) epistemic std of each share (the same for every class)
    mean: np.ndarray  # (n, C, 3) velocity of each mode
    std: np.ndarray  # (n, C, 3) its std (predictive, or epistemic)
    weight: np.ndarray  # (n, C) the class's data within the kernel's reach (:meth:`Posterior.data_weight`)
    # (n, C, 3) the noise variance within std^2 of each heading sector's mode, which a known
    # heading can narrow (:func:`bdf.sectors.heading_mode`); zero for the slow class and for
    # a map of one class, which no heading narrows
    heading_noise: np.ndarray

    def answer(self, sectors: Sectors, heading_deg=None) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std (..., 3): the mixture's moments (at points or on a grid), or with
        ``heading_deg`` (one, or one per point) the mode of that heading: the two nearest
        sectors' modes pooled (:func:`bdf.sectors.heading_mode`; the one mode of a map of one
        class)."""
        if self.share.shape[-1] == 1:
            return self.mean[..., 0, :], self.std[..., 0, :]
        if heading_deg is None:
            return mixture_moments(self.share, self.mean, self.std)
        heading = np.broadcast_to(np.asarray(heading_deg, float), self.share.shape[:-1])
        k0, k1, weight = sectors.nearest_two(heading)
        return heading_mode(sectors, heading, weight, *self._of(k0), *self._of(k1))

    def flown(self, sectors: Sectors, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std (n, 3) of the mode of the heading each velocity ``V`` (n, 3) flies
        (:meth:`answer`), or the slow class's below ``sectors.slow_mps``: how a held-out row
        of known velocity is scored at its own heading (the conditional answer)."""
        if self.share.shape[-1] == 1:
            return self.answer(sectors)
        mean, std = self.answer(sectors, np.degrees(np.arctan2(V[:, 0], V[:, 1])))
        slow = (sectors.classify(V) == sectors.directions)[:, None]
        return np.where(slow, self.mean[:, -1], mean), np.where(slow, self.std[:, -1], std)

    def as_one_class(self) -> Modes:
        """The mixture as one mode: its moments, share 1, all the data's weight."""
        mean, std = mixture_moments(self.share, self.mean, self.std)
        shape = self.share.shape[:-1]
        weight = self.weight.sum(axis=-1, keepdims=True)
        one = (np.ones((*shape, 1)), np.zeros(shape), mean[..., None, :], std[..., None, :], weight)
        return Modes(*one, np.zeros_like(one[3]))

    def heading_share(self, sectors: Sectors, heading_deg) -> np.ndarray:
        """(...): the share of traffic of a heading, pooled as its mode (:meth:`answer`)."""
        k0, k1, weight = (np.broadcast_to(a, self.share.shape[:-1]) for a in sectors.nearest_two(heading_deg))
        s0, s1 = (np.take_along_axis(self.share, k[..., None], axis=-1)[..., 0] for k in (k0, k1))
        return weight * s0 + (1.0 - weight) * s1

    def _of(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mean, std and heading noise (..., 3) of class ``k`` (...) at each point."""
        at = k[..., None, None]
        return tuple(
            np.take_along_axis(a, at, axis=-2)[..., 0, :] for a in (self.mean, self.std, self.heading_noise)
        )

    @property
    def prior_only(self) -> np.ndarray:
        """(n, C): the class has no data within the kernel's reach (its weight is below
        :data:`KNOWN_WEIGHT`), so its mode there is only its prior: the class's mean velocity
        near there (in its layer of hinges), and its share the region's overall share where
        no class has data."""
        return self.weight < KNOWN_WEIGHT


class Posterior:
    """What a factorisation of the evidence gives: weights now, the variance density on demand.

    Derived data only (tiles cache these per version); the evidence is the source of truth.
    With ``noise_lattice`` (and the evidence's moments), the noise term of the predictive
    variance is local (:mod:`bdf.noise`) with prior weight ``noise_prior``.
    """

    def __init__(
        self,
        grid: HingeGrid,
        kernel: Kernel,
        evidence: Evidence,
        alpha,
        beta,
        noise_lattice=None,
        noise_prior=None,
        start=None,
        prior_weights=None,
        anchor=None,
        density=True,
        settle=True,
    ):
        self.grid, self.kernel = grid, kernel
        self.gamma, self.cutoff = np.array(kernel.gamma), kernel.cutoff
        self.noise_lattice, self.noise_prior = noise_lattice, noise_prior
        self._moments = None if evidence.moments is None else noise.table(noise_lattice, evidence.moments)
        # where the data are (:meth:`data_weight`); a mixture keeps its classes' itself
        self._density = evidence.density if density else None
        self.stencil = sparse.stencil_on(grid, kernel)
        #: alpha or beta came from evidence maximisation ("auto" and some data)
        self.fitted = (isinstance(alpha, str) or isinstance(beta, str)) and evidence.count > 0
        # The prior N(w0, alpha^-1 I) of the weights (w0 = ``prior_weights``, zero unless
        # given: a mode of a directional map, :class:`Mixture`): the search and the solves
        # see the observations less the prior's field, v - Phi w0, whose statistics are
        # b - G w0 and v^T v - 2 w0^T b + w0^T G w0; the weights are w0 plus their solution.
        band = evidence.gram_band(self.stencil)
        proj, v_sq, w0 = evidence.proj, evidence.v_sq, 0.0
        if prior_weights is not None:
            w0 = prior_weights
            G_w0 = sparse.band_product(self.stencil, band, w0)
            v_sq = v_sq - 2.0 * np.einsum("mc,mc->c", w0, proj) + np.einsum("mc,mc->c", w0, G_w0)
            proj = proj - G_w0
        #: (3,) the data's mean square difference from the prior mean's field (zero without
        #: data): how far they lie from what the prior expects (:class:`Mixture`'s widening)
        self.prior_misfit = np.maximum(v_sq, 0.0) / evidence.count if evidence.count > 0 else np.zeros(3)
        fit = hyperparameters.fit_evidence(
            self.stencil, band, proj, v_sq, evidence.count, alpha, beta, start, anchor, settle
        )
        self.alpha, self.beta, sols = fit.alpha, fit.beta, fit.solutions
        self.factorisations, self.settled, self.evidence_gap = fit.factorisations, fit.settled, fit.gap
        self.at_bound = fit.at_bound
        #: a region's map (set by :func:`bdf.region.map.compute_posterior`): the fastest
        #: plausible horizontal speed by altitude (a ``SpeedBound``), and how the map compares
        self.speed_bound = None
        self.plausibility: dict | None = None
        #: where a next search of "auto" hyperparameters best starts (ratios alpha / beta):
        #: the optimum, or where the search pointed when it stopped within a nat of it
        self.next_start = fit.next_start
        self.log_evidence = np.array(
            [
                hyperparameters.log_evidence(s, self.alpha, self.beta, evidence.count)[c]
                for c, s in enumerate(sols)
            ]
        )
        self.weights = w0 + np.stack([s.weights[:, c] for c, s in enumerate(sols)], axis=1)
        self._solutions = sols
        self._variance = None
        # the weights as the point gather reads them, made by the first :meth:`mean` (a
        # mixture's modes never make theirs: it gathers every mode's weights in one table)
        self._mean_table = None

    def data_weight(self, X: np.ndarray) -> np.ndarray:
        """(n, 1): the data's weight within the kernel's reach of each point,
        ``sum_i w_i k(x, x_i)``: 1 for an observation of weight 1 at ``x``, 0.01 for one at
        the kernel's 1 % reach. From the data's density (the statistics' ``density``, of the
        points without input noise), gathered on its lattice: ``k`` is its kernel's
        convolution with itself."""
        return self._midpoints(X)[1]

    def mean(self, X: np.ndarray) -> np.ndarray:
        if self._mean_table is None:
            self._mean_table = LaneTable.of(self.weights.reshape(*self.grid.shape, 3), self._lanes())
        return features.gather(self.grid, X, self._mean_table, self.gamma, cutoff=self.cutoff)

    def variance_table(self) -> tuple[LaneTable, list[int]]:
        """The variance densities on the midpoint lattice (one per distinct factorisation)
        and the one each component uses; ``phi^T Sigma_c phi`` is their gather over beta_c.
        The data's density is the table's last column (one gather answers both)."""
        if self._variance is None:
            densities, columns = self._variance_density()
            if self._density is not None:
                densities = np.concatenate([densities, self._density[..., None]], axis=-1)
            self._variance = LaneTable.of(densities, self._lanes(midpoints=True)), columns
        return self._variance

    def _lanes(self, midpoints=False) -> int:
        """The chunk width of a query table on the hinge lattice, or on its midpoints."""
        if midpoints:
            return features.lanes_for(self.grid.midpoints(), 2.0 * self.gamma, self.cutoff)
        return features.lanes_for(self.grid, self.gamma, self.cutoff)

    def _midpoints(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One gather of the midpoint lattice at ``X``: ``phi(x)^T Sigma_c phi(x)`` per
        component (n, 3), and :meth:`data_weight` (n, 1)."""
        densities, columns = self.variance_table()
        at = features.gather(
            self.grid.midpoints(), X, densities, 2.0 * self.gamma, cutoff=self.cutoff, block=MIDPOINT_BLOCK
        )
        return np.maximum(at[:, columns] / self.beta, 0.0), _normalised(self.grid, self.gamma, at[:, -1:], X)

    def predict_grid(self, axes, include_noise=True) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance (predictive, or epistemic without the noise) on the grid
        ``axes`` (three 1-D arrays), each (nx, ny, nz, 3); separable, see
        :func:`features.gather_grid`."""
        mean, var, _ = self._grid(axes, include_noise)
        return mean, var

    def answer_grid(self, axes, include_noise=True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`answer` on the grid ``axes``: mean and std (nx, ny, nz, 3) and
        :meth:`data_weight` (nx, ny, nz, 1), each lattice gathered once."""
        mean, var, at = self._grid(axes, include_noise)
        return mean, np.sqrt(var), _normalised_grid(self.grid, self.gamma, at, axes)

    def _grid(self, axes, include_noise):
        """Mean and variance on the grid ``axes``, and the data's density gathered there
        (nx, ny, nz, 1; None for a mode, which keeps none): one gather per lattice."""
        densities, columns = self.variance_table()
        mean = features.gather_grid(
            self.grid, axes, self.weights.reshape(*self.grid.shape, 3), self.gamma, cutoff=self.cutoff
        )
        at = features.gather_grid(
            self.grid.midpoints(), axes, densities, 2.0 * self.gamma, cutoff=self.cutoff
        )
        scatter = self.noise_variance_grid(axes, mean) if include_noise else 0.0
        density = at[..., -1:] if self._density is not None else None
        return mean, np.maximum(at[..., columns] / self.beta, 0.0) + scatter, density

    def noise_variance_grid(self, axes, mean: np.ndarray):
        """:meth:`noise_variance` on the grid ``axes`` where the posterior mean is ``mean``
        (nx, ny, nz, 3): ``1/beta`` (3,), or the local estimate on the grid."""
        if self._moments is None:
            return 1.0 / self.beta
        return noise.noise_variance_grid(
            self.noise_lattice, self._moments, axes, mean, self.beta, self.noise_prior
        )

    def noise_variance(self, X: np.ndarray, mean: np.ndarray) -> np.ndarray:
        """The noise term of the predictive variance at ``X`` (n, 3): ``1/beta``, or the
        local estimate of :mod:`bdf.noise` where the posterior mean is ``mean``."""
        if self._moments is None:
            return np.broadcast_to(1.0 / self.beta, mean.shape)
        return noise.noise_variance(self.noise_lattice, self._moments, X, mean, self.beta, self.noise_prior)

    def predict(self, X: np.ndarray, return_std=False, include_noise=True):
        """Mean (N, 3), and the std if asked: predictive, or epistemic without ``1/beta``."""
        return self.answer(X, include_noise)[:2] if return_std else self.mean(X)

    def answer(self, X: np.ndarray, include_noise=True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mean and std (n, 3), as :meth:`predict`, and :meth:`data_weight` (n, 1): each
        lattice gathered once."""
        mean = self.mean(X)
        var, weight = self._midpoints(X)
        if include_noise:
            var = var + self.noise_variance(X, mean)
        return mean, np.sqrt(var), weight

    def predict_modes(self, X: np.ndarray, include_noise=True) -> Modes:
        """The one mode of a map of one class."""
        mean, std, weight = self.answer(X, include_noise)
        n = len(X)
        return Modes(np.ones((n, 1)), np.zeros(n), mean[:, None], std[:, None], weight, np.zeros((n, 1, 3)))

    def predict_grid_modes(self, axes, include_noise=True) -> Modes:
        """The one mode of a map of one class, on the grid ``axes``."""
        mean, std, weight = self.answer_grid(axes, include_noise)
        n = mean.shape[:3]
        one = (np.ones((*n, 1)), np.zeros(n), mean[..., None, :], std[..., None, :], weight)
        return Modes(*one, np.zeros_like(one[3]))

    def compact(self) -> Posterior:
        """Compute the variance density and the gather tables now and drop the factors:
        what a cache keeps (a few times the midpoint lattice)."""
        self.variance_table()
        self._solutions = None
        return self

    @property
    def nbytes(self) -> int:
        """Memory held by the arrays of this posterior."""
        held = self.weights.nbytes + sum(
            a.nbytes for a in (self._density, self._moments, self._mean_table) if a is not None
        )
        if self._variance is not None:
            held += self._variance[0].nbytes
        if self._solutions is not None:
            held += sum(s.factor.nbytes for s in {id(s): s for s in self._solutions}.values())
        return held

    def _variance_density(self):
        # Sigma_c = (G + lam I)^-1 / beta_c on the stencil (selected inversion); one
        # density per distinct factorisation
        densities, columns = {}, []
        for sol in self._solutions:
            if id(sol) not in densities:
                hyperparameters.check_abandoned()
                inverse = sol.factor.inverse_band()
                densities[id(sol)] = sparse.band_density(self.stencil, inverse, self.grid.midpoints())
            columns.append(list(densities).index(id(sol)))
        return np.stack(list(densities.values()), axis=-1), columns


def _normalised(grid: HingeGrid, gamma, at: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``sum_i w_i exp(-sum_d gamma_d (x_d - x_id)^2)`` (n, C) from data densities on the
    midpoint lattice (kernel ``2 gamma``, :mod:`bdf.statistics`; C of them) gathered at ``X``
    with the same kernel (``at``): each pair of an observation and ``x`` meets at their
    midpoint with the lattice's sum of ``exp(-4 gamma (g - midpoint)^2)``, which
    :func:`_lattice_sum` divides out (near ``x``: it falls to half at the lattice's edge)."""
    norm = (_lattice_sum(grid, gamma, 0, X[:, 0]) * _lattice_sum(grid, gamma, 1, X[:, 1]))[:, None]
    norm *= _lattice_sum(grid, gamma, 2, X[:, 2])[:, None]
    return np.divide(np.maximum(at, 0.0), norm, out=np.zeros_like(at), where=norm > 0)  # 0 far outside


def _normalised_grid(grid: HingeGrid, gamma, at: np.ndarray, axes) -> np.ndarray:
    """:func:`_normalised` of data densities gathered on the grid ``axes`` (nx, ny, nz, C)."""
    nx, ny, nz = (_lattice_sum(grid, gamma, d, np.asarray(axes[d], float)) for d in range(3))
    norm = (nx[:, None, None] * ny[None, :, None] * nz[None, None, :])[..., None]
    return np.divide(np.maximum(at, 0.0), norm, out=np.zeros_like(at), where=norm > 0)


#: A mode's share is at least this fraction of its class's overall share (:class:`Mixture`):
#: on Paris at 8 sectors, raising the shares the smoother cut to 0 gains 0.08 nats of
#: held-out mixture MSLL at 0.01 of the moments' (``bench/bench_tracks.py --prior-reach 4``)
SHARE_FLOOR = 0.01
#: erf(z) is exactly 1 in float64 from here on: no need to evaluate it there.
ERF_ONE = 6.0
#: A mode's variance gains this fraction of its class's mean square misfit about its prior
#: mean (:attr:`Posterior.prior_misfit`), times the square of the share of its epistemic
#: variance that is the prior's (:class:`Mixture`). On the Paris flight split
#: (``bench/bench_directions.py --directions 16,auto --spread-share 0.5,1``): at 16 sectors
#: held-out MSLL -1.007 / -1.002 and conditional cov95 0.969 / 0.973 with 0.5 / 1; the
#: choice's folds keep 8 sectors with 0.5 (their scores within a standard error), 16 with 1.
#: Half the class's velocity variance over the region instead (the rule before) kept 24, whose
#: map widened too much where the local prior mean already knows the flow (held-out MSLL
#: -0.980, cov95 0.977); none: 8 (the folds could not tell 8 from 32)
CLASS_SPREAD_SHARE = 1.0


def _lattice_sum(grid: HingeGrid, gamma, d: int, x: np.ndarray) -> np.ndarray:
    """``sum_g exp(-4 gamma_d (g - x)^2)`` over the midpoint lattice's axis ``d``, by the
    integral over its cells (the midpoint rule; inside, the sum's ripple is
    ``2 exp(-pi^2 / (gamma_d spacing_d^2))`` of it, below 1e-4 at the usual
    ``gamma = 1 / spacing^2``)."""
    g, h = float(gamma[d]), float(grid.step[d]) / 2.0
    lo, hi = float(grid.origin[d]) - h / 2, float(grid.origin[d]) + (grid.shape[d] - 1) * 2.0 * h + h / 2
    inside = math.sqrt(math.pi / (4.0 * g)) / h  # the sum where both edges are beyond ERF_ONE widths
    return _edge_integral(np.ascontiguousarray(x, float), 2.0 * math.sqrt(g), lo, hi, inside)


@numba.njit(cache=True, nogil=True)
def _edge_integral(x, root, lo, hi, inside):  # pragma: no cover (compiled)
    """:func:`_lattice_sum` at each of ``x``: ``inside`` times the share of the Gaussian of
    width ``1 / root`` about ``x`` that lies in ``[lo, hi]`` (erf only within
    :data:`ERF_ONE` widths of an edge: one pass, no temporaries; a query's points are many)."""
    out = np.empty_like(x)
    for p in range(len(x)):
        a, b = root * (hi - x[p]), root * (x[p] - lo)
        out[p] = inside if a >= ERF_ONE and b >= ERF_ONE else inside * 0.5 * (math.erf(a) + math.erf(b))
    return out


#: A mode's prior mean at a hinge: its class's mean velocity over this many hinges either
#: side horizontally, in the hinge's layer (:func:`_local_prior`)
LOCAL_PRIOR_HINGES = 4
#: ... shrunk toward the class's mean in the layer by this many observations' weight
LOCAL_PRIOR_ROWS = 1.0


def _local_prior(evidence: Evidence, grid: HingeGrid, gamma) -> np.ndarray:
    """A mode's prior mean weights (M, 3): at each hinge, the class's mean velocity near it
    (its data's ``Phi^T v`` over their ``Phi^T 1``, summed over the hinge's layer within
    :data:`LOCAL_PRIOR_HINGES` horizontally, with :data:`LOCAL_PRIOR_ROWS` observations of
    the layer's own mean), over the features' sum (``Phi w0`` is then that mean, away from
    the lattice's edges). Away from its data a heading sector's mode reverts to how that
    class flies there, not to standing still; and a flow faster than its layer's mean is
    fitted by a small residual near it rather than by large weights that overshoot above
    and below its rows (a prior mean per layer alone made an 8-sector mode of the Paris
    demo extrapolate to 253 m/s where its rows fly at most 223: ``bench/bench_tracks.py``).
    The layer's mean is the class's mean where no observation reaches the layer (zero for a
    class without data). A function of the additive statistics: uploads in any split give
    the same prior."""
    overall = evidence.v_sum / evidence.count if evidence.count > 0 else np.zeros(3)
    proj = evidence.proj.reshape(*grid.shape, 3)
    mass = evidence.mass.reshape(grid.shape)
    layer_mass = mass.sum(axis=(0, 1))
    layer = np.where(
        layer_mass[:, None] > 0,
        proj.sum(axis=(0, 1)) / np.where(layer_mass > 0, layer_mass, 1.0)[:, None],
        overall,
    )
    # the sum of a point's features inside the lattice: sqrt(pi / (gamma step^2)) per axis
    features_sum = float(np.prod(np.sqrt(np.pi / (np.asarray(gamma, float) * grid.step**2))))
    width = 2 * LOCAL_PRIOR_HINGES + 1
    near_proj = ndimage.uniform_filter(proj, size=(width, width, 1, 1), mode="constant") * width**2
    near_mass = ndimage.uniform_filter(mass, size=(width, width, 1), mode="constant") * width**2
    pseudo = LOCAL_PRIOR_ROWS * features_sum
    local = (near_proj + pseudo * layer) / (np.maximum(near_mass, 0.0) + pseudo)[..., None]
    return (local / features_sum).reshape(-1, 3)


def _per_row(hyper, rows: int) -> list:
    """A hyperparameter for each of ``rows`` posteriors: "auto" for all, or the row of a
    (3,) value broadcast, or of a (rows, 3) one."""
    return [hyper] * rows if isinstance(hyper, str) else list(np.broadcast_to(hyper, (rows, 3)))


class _MixtureTables(NamedTuple):
    """What a :class:`Mixture`'s queries gather (:meth:`Mixture._gather_tables`)."""

    weights: LaneTable  # hinge lattice: every mode's mean weights (3 C), then the share weights (C)
    answer: LaneTable  # midpoint lattice: the modes' variance densities, then all the data's density
    modes: LaneTable  # midpoint lattice: the one-class map's variance densities, each class's data density
    columns: np.ndarray  # (C, 3): each mode's variance column in ``answer``
    total_columns: np.ndarray  # (3,): the map with one class's in ``modes``


class Mixture:
    """The posterior of a directional map (:mod:`bdf.sectors`): one :class:`Posterior`
    per class (its *mode*) and the share field.

    The shares regress each class's indicator on the same features, with the map's overall
    shares as prior mean: ``share_c(x) = p_c + phi(x)^T (G + lam I)^-1 Phi^T (y_c - p_c)``,
    with ``G`` and ``lam`` of the map with one class (its factorisation, no other). They sum
    to 1 exactly; values below :data:`SHARE_FLOOR` times the overall share (the linear
    smoother undershoots next to sharp edges, down to negative values) are raised to it and
    the rest renormalised: a class that flies somewhere in the region is never certainly
    absent, or a held-out flight of it where the smoother undershoots has no density. Their
    epistemic std is ``sqrt(phi^T (G + lam I)^-1 phi / beta_share)``, ``beta_share`` at its
    evidence maximum.

    Each mode's prior mean is its class's mean velocity near each hinge
    (:func:`_local_prior`), as the shares' is the overall share: away from a class's data
    its mode reverts to how that class flies there, not to standing still. How far the
    class's flights may lie from that mean there is not the prior's amplitude, which the
    evidence fits where the class flies (at 16 sectors on Paris, a std of 2-3 m/s about the
    local mean): a flight unlike the class's others would be predicted with that confidence.
    So a mode's variance gains its class's mean square misfit about that mean (per
    component, :attr:`Posterior.prior_misfit`; :data:`CLASS_SPREAD_SHARE` of it) times
    ``r^2``, ``r`` the share of the mode's epistemic variance that is the prior's
    (``phi^T Sigma phi / beta`` over ``phi^T phi / alpha``, the latter taken inside the
    lattice; at most 1): next to nothing where the class's data pin the mode down, the
    class's spread about its prior mean where they do not.

    Hyperparameters: "auto" fits the map with one class (``total``, whose factorisation the
    shares use) and each mode at its own evidence maximum: traffic classes differ in how
    smooth and how noisy they are (sharing the map's ratio alpha / beta fits faster and
    loses mixture MSLL on Paris: ``bench/bench_core.py --directions``).
    Fixed values are (3,) for all, or (1 + C, 3): the map with one class, then each class.

    The modes are fitted and their variance densities computed at construction, side by
    side in a thread per core (their algebra releases the GIL, :mod:`bdf.sparse._lapack`): a
    directional map is only ever queried whole. Each mode drops its factor once its variance
    density is made, so that a map's peak memory is the map with one class's factor and one
    mode's per thread, whatever the number of classes.
    """

    def __init__(
        self,
        grid,
        kernel: Kernel,
        evidence: SectorEvidence,
        alpha,
        beta,
        noise_lattice,
        noise_prior,
        sectors,
        start=None,
        settle=True,
    ):
        C = sectors.classes
        self.sectors, self.grid, self.kernel = sectors, grid, kernel
        self.gamma, self.cutoff = np.array(kernel.gamma), kernel.cutoff
        alphas, betas = _per_row(alpha, 1 + C), _per_row(beta, 1 + C)
        rest = (noise_lattice, noise_prior)
        total = evidence.total()
        starts = [None] * (1 + C) if start is None else list(np.broadcast_to(start, (1 + C, 3)))
        self.total = Posterior(
            grid, kernel, total, alphas[0], betas[0], *rest, start=starts[0], density=False, settle=settle
        )
        anchor = float(np.mean(self.total.alpha / self.total.beta))  # a mode's cold start

        def mode(c):
            e = evidence.classes[c]
            post = Posterior(
                grid,
                kernel,
                e,
                alphas[1 + c],
                betas[1 + c],
                *rest,
                start=starts[1 + c],
                prior_weights=_local_prior(e, grid, self.gamma),
                anchor=anchor,
                density=False,
                settle=settle,
            )
            return post.compact()  # its factor goes now: memory bounded by a factor per thread

        # the modes side by side on the cores (their algebra releases the GIL), the most
        # data first so that the threads end together; and the total's variance meanwhile
        by_count = sorted(range(C), key=lambda c: -evidence.classes[c].count)
        _, *fitted = _blas.in_threads(
            [self.total.variance_table, *(functools.partial(mode, c) for c in by_count)]
        )
        of_class = dict(zip(by_count, fitted, strict=True))
        self.modes = [of_class[c] for c in range(C)]
        # the classes' data densities side by side, gathered with the variance densities
        self._densities = np.stack([e.density for e in evidence.classes], axis=-1)
        # a mode's widening (see the class doc): r = its epistemic variance x ``_reliance``
        # (at most 1), r^2 times ``_spread``
        features_sq = float(np.prod(np.sqrt(np.pi / (2.0 * self.gamma)) / grid.step))  # phi^T phi inside
        self._reliance = np.stack([m.alpha for m in self.modes]) / features_sq
        self._spread = CLASS_SPREAD_SHARE * np.stack([m.prior_misfit for m in self.modes])
        self.fitted = self.total.fitted
        self.speed_bound = None  # as the Posterior's
        self.plausibility: dict | None = None
        # the share field, on the factorisation of the map with one class
        counts = np.array([e.count for e in evidence.classes])
        n = counts.sum()
        self.prior_share = counts / n if n > 0 else np.full(C, 1.0 / C)
        rhs = np.stack([e.mass for e in evidence.classes], axis=1) - total.mass[:, None] * self.prior_share
        sol = self.total._solutions[0]
        self.share_weights = sol.factor.solve(rhs)
        residual = np.sum(counts * (1.0 - self.prior_share)) - np.sum(rhs * self.share_weights)
        self.share_beta = (
            min(C * n / max(residual, 1e-300), hyperparameters.MAX_AUTO_BETA)
            if n > 0
            else hyperparameters.EMPTY_BETA
        )
        self._tables = None

    @property
    def alpha(self) -> np.ndarray:
        """(1 + C, 3): the map with one class, then each mode."""
        return np.stack([self.total.alpha, *(m.alpha for m in self.modes)])

    @property
    def beta(self) -> np.ndarray:
        return np.stack([self.total.beta, *(m.beta for m in self.modes)])

    @property
    def log_evidence(self) -> np.ndarray:
        return np.stack([self.total.log_evidence, *(m.log_evidence for m in self.modes)])

    @property
    def settled(self) -> bool:
        return self.total.settled and all(m.settled for m in self.modes)

    @property
    def at_bound(self) -> bool:
        """A search of the map or of a mode ended at its range's floor or top."""
        return self.total.at_bound or any(m.at_bound for m in self.modes)

    @property
    def evidence_gap(self) -> float:
        """Nats the map with one class and the modes lack from their evidence maxima, summed."""
        return self.total.evidence_gap + sum(m.evidence_gap for m in self.modes)

    @property
    def next_start(self) -> np.ndarray:
        return np.stack([self.total.next_start, *(m.next_start for m in self.modes)])

    @property
    def factorisations(self) -> int:
        """Factorisations the fit took (the map with one class's and every mode's)."""
        return self.total.factorisations + sum(m.factorisations for m in self.modes)

    def _share(self, weights_at, base_variance):
        """Shares from the gathered share weights (n, C), and their std."""
        raw = np.maximum(self.prior_share + weights_at, SHARE_FLOOR * self.prior_share)
        share = raw / raw.sum(axis=1, keepdims=True)
        return share, np.sqrt(np.maximum(base_variance, 0.0) / self.share_beta)

    def _widened(self, c: int, epistemic: np.ndarray) -> np.ndarray:
        """Mode ``c``'s epistemic variance (..., 3) with its class's spread where the prior
        holds it (the class doc)."""
        return _widen(epistemic, self._reliance[c], self._spread[c])

    def _gather_tables(self):
        """Every mode's weights and the share weights side by side on the hinge lattice; on
        the midpoint lattice, what every answer needs (each mode's variance densities, then
        all the data's density) and what only the modes need (the map with one class's
        variance densities, then each class's data density); with the modes' columns and
        the map with one class's. A query gathers each table it needs once."""
        if self._tables is None:
            weights = np.concatenate([*(m.weights for m in self.modes), self.share_weights], axis=1)
            densities, columns, offset = [], [], 0
            for post in self.modes:
                d, c = post.variance_table()
                densities.append(d.array())
                columns.append(offset + np.asarray(c))
                offset += d.channels
            total, total_columns = self.total.variance_table()
            lanes, midpoint_lanes = self.total._lanes(), self.total._lanes(midpoints=True)
            self._tables = _MixtureTables(
                LaneTable.of(weights.reshape(*self.grid.shape, -1), lanes),
                LaneTable.of(
                    np.concatenate([*densities, self._densities.sum(axis=-1, keepdims=True)], axis=-1),
                    midpoint_lanes,
                ),
                LaneTable.of(np.concatenate([total.array(), self._densities], axis=-1), midpoint_lanes),
                np.array(columns),
                np.asarray(total_columns),
            )
        return self._tables

    def _gather(self, X: np.ndarray, modes: bool = False):
        """The tables at ``X``: the weights (n, 4 C: the modes' means, then the share
        weights), what every answer needs (n, D + 1: the modes' variance densities, then all
        the data's density), and with ``modes`` what the modes need too (n, E + C)."""
        tables = self._gather_tables()
        midpoints, k = self.grid.midpoints(), 2.0 * self.gamma
        at = features.gather(self.grid, X, tables.weights, self.gamma, cutoff=self.cutoff)
        var = features.gather(midpoints, X, tables.answer, k, cutoff=self.cutoff, block=MIDPOINT_BLOCK)
        if not modes:
            return at, var, None
        extra = features.gather(midpoints, X, tables.modes, k, cutoff=self.cutoff, block=MIDPOINT_BLOCK)
        return at, var, extra

    def _gather_grid(self, axes, modes: bool = False):
        """:meth:`_gather` on the grid ``axes``, the grid's shape first (separable)."""
        tables = self._gather_tables()
        midpoints, k = self.grid.midpoints(), 2.0 * self.gamma
        at = features.gather_grid(self.grid, axes, tables.weights, self.gamma, cutoff=self.cutoff)
        var = features.gather_grid(midpoints, axes, tables.answer, k, cutoff=self.cutoff)
        extra = features.gather_grid(midpoints, axes, tables.modes, k, cutoff=self.cutoff) if modes else None
        return at, var, extra

    def _moments(self, at, var, noise_of) -> tuple[np.ndarray, np.ndarray]:
        """The mixture's mean and variance (n, 3) from the tables gathered at n points
        (:meth:`_gather`), without the modes' (n, C, 3) arrays (:func:`_mixture_moments`);
        ``noise_of(mode, mean)``: a mode's local noise variance where its mean is ``mean``
        (n, 3), or None for none."""
        C = len(self.modes)
        if noise_of is None:
            noise = np.zeros((C, 1, 3))
        elif all(m._moments is None for m in self.modes):  # global noise: 1 / beta each
            noise = 1.0 / np.stack([m.beta for m in self.modes])[:, None]
        else:
            noise = np.stack(
                [noise_of(m, at[:, 3 * c : 3 * c + 3]).reshape(-1, 3) for c, m in enumerate(self.modes)]
            )
        columns = self._gather_tables().columns
        inverse_beta = 1.0 / np.stack([m.beta for m in self.modes])
        mean, variance = np.empty((len(at), 3)), np.empty((len(at), 3))
        _mixture_moments(
            at,
            var,
            self.prior_share,
            SHARE_FLOOR * self.prior_share,
            columns,
            inverse_beta,
            self._reliance,
            self._spread,
            noise,
            mean,
            variance,
        )
        return mean, variance

    def predict_modes(self, X: np.ndarray, include_noise=True) -> Modes:
        tables = self._gather_tables()
        C = len(self.modes)
        at, var, extra = self._gather(X, modes=True)
        mean = at[:, : 3 * C].reshape(len(X), C, 3)
        std, heading_noise = np.empty_like(mean), np.zeros_like(mean)
        for c, mode in enumerate(self.modes):
            v = self._widened(c, np.maximum(var[:, tables.columns[c]] / mode.beta, 0.0))
            if include_noise:
                scatter = mode.noise_variance(X, mean[:, c])
                v = v + scatter
                if c < self.sectors.directions:
                    heading_noise[:, c] = scatter
            std[:, c] = np.sqrt(v)
        # phi^T (G + lam I)^-1 phi, from the map with one class's first factorisation
        share, share_std = self._share(at[:, 3 * C :], extra[:, tables.total_columns[0]])
        weight = _normalised(self.grid, self.gamma, extra[:, -C:], X)
        return Modes(share, share_std, mean, std, weight, heading_noise)

    def answer(self, X: np.ndarray, include_noise=True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The mixture's mean and std (n, 3) and all the data's weight (n, 1), as
        :meth:`Posterior.answer`: without the modes' arrays, or the tables only they need."""
        at, var, _ = self._gather(X)
        local = (lambda m, mean: m.noise_variance(X, mean)) if include_noise else None
        mean, variance = self._moments(at, var, local)
        return mean, np.sqrt(variance), _normalised(self.grid, self.gamma, var[:, -1:], X)

    def data_weight(self, X: np.ndarray) -> np.ndarray:
        """(n, C): each class's data within the kernel's reach (:meth:`Posterior.data_weight`)."""
        return self.predict_modes(X).weight

    def predict(self, X: np.ndarray, return_std=False, include_noise=True):
        """The mixture's mean (n, 3), and its std if asked (moments over the modes)."""
        mean, std, _ = self.answer(X, include_noise)
        return (mean, std) if return_std else mean

    def predict_grid(self, axes, include_noise=True) -> tuple[np.ndarray, np.ndarray]:
        """The mixture's mean and variance on the grid ``axes`` (see :meth:`Posterior.predict_grid`)."""
        mean, var, _ = self._grid(axes, include_noise)
        return mean, var

    def answer_grid(self, axes, include_noise=True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`answer` on the grid ``axes`` (see :meth:`Posterior.answer_grid`)."""
        mean, var, at = self._grid(axes, include_noise)
        return mean, np.sqrt(var), _normalised_grid(self.grid, self.gamma, at, axes)

    def _grid(self, axes, include_noise):
        """The mixture's mean and variance on the grid ``axes``, and all the data's density
        gathered there (nx, ny, nz, 1), from one gather per lattice."""
        at, var, _ = self._gather_grid(axes)
        n = at.shape[:3]
        local = (lambda m, mean: m.noise_variance_grid(axes, mean.reshape(*n, 3))) if include_noise else None
        mean, variance = self._moments(at.reshape(-1, at.shape[-1]), var.reshape(-1, var.shape[-1]), local)
        return mean.reshape(*n, 3), variance.reshape(*n, 3), var[..., -1:]

    def predict_grid_modes(self, axes, include_noise=True) -> Modes:
        """:class:`Modes` on the grid ``axes``, each array with the grid's shape first: like
        :meth:`predict_modes`, each lattice's tables gathered once for every class."""
        tables = self._gather_tables()
        C = len(self.modes)
        at, var, extra = self._gather_grid(axes, modes=True)
        n = at.shape[:3]
        mean = at[..., : 3 * C].reshape(*n, C, 3)
        std = var[..., tables.columns]  # (nx, ny, nz, C, 3), then in place
        std /= np.stack([m.beta for m in self.modes])
        np.maximum(std, 0.0, out=std)
        heading_noise = np.zeros_like(mean)
        for c, mode in enumerate(self.modes):
            std[..., c, :] = self._widened(c, std[..., c, :])
            if include_noise:
                scatter = mode.noise_variance_grid(axes, mean[..., c, :])
                std[..., c, :] += scatter
                if c < self.sectors.directions:
                    heading_noise[..., c, :] = scatter
        np.sqrt(std, out=std)
        # phi^T (G + lam I)^-1 phi, from the map with one class's first factorisation
        share, share_std = self._share(
            at[..., 3 * C :].reshape(-1, C), extra[..., tables.total_columns[0]].ravel()
        )
        weight = _normalised_grid(self.grid, self.gamma, extra[..., -C:], axes)
        return Modes(share.reshape(*n, C), share_std.reshape(n), mean, std, weight, heading_noise)

    def compact(self) -> Mixture:
        self.total.compact()
        for m in self.modes:
            m.compact()
        self._gather_tables()
        return self

    @property
    def nbytes(self) -> int:
        held = self.share_weights.nbytes + self._densities.nbytes + self.total.nbytes
        held += sum(m.nbytes for m in self.modes)
        if self._tables is not None:
            tables = self._tables
            held += tables.weights.nbytes + tables.answer.nbytes + tables.modes.nbytes
        return held


@numba.vectorize(["f8(f8, f8, f8)"], cache=True)
def _widen(epistemic, reliance, spread):  # pragma: no cover (compiled)
    """A mode's epistemic variance widened by its class's ``spread`` where the prior holds
    it: ``r = min(epistemic x reliance, 1)``, plus ``r^2 spread`` (:class:`Mixture`); a
    ufunc, so that the points, the grids and :func:`_mixture_moments` apply one rule."""
    return epistemic + min(epistemic * reliance, 1.0) ** 2 * spread


@numba.njit(cache=True, nogil=True)
def _mixture_moments(
    at, var, prior, floor, columns, inverse_beta, reliance, spread, noise, mean, variance
):  # pragma: no cover
    """:func:`bdf.sectors.mixture_moments` of the modes :meth:`Mixture.predict_modes`
    makes, point by point from the gathered tables (no (n, C, 3) temporaries: grids are
    large): the shares (``prior`` plus share weights ``at[:, 3C:]``, at least ``floor``,
    renormalised), each mode's mean ``at[:, 3c:3c+3]`` and variance (its density column
    over beta, at least 0, widened by ``reliance`` and ``spread`` (:func:`_widen`), plus
    ``noise[c, 0 or p]``), then the mixture's mean and variance into ``mean`` and
    ``variance`` (n, 3)."""
    C = len(prior)
    share = np.empty(C)
    for p in range(at.shape[0]):
        total = 0.0
        for c in range(C):
            share[c] = max(prior[c] + at[p, 3 * C + c], floor[c])
            total += share[c]
        for c in range(C):
            share[c] /= total
        row = min(p, noise.shape[1] - 1)
        for d in range(3):
            first, second = 0.0, 0.0
            for c in range(C):
                mu = at[p, 3 * c + d]
                v = _widen(max(var[p, columns[c, d]] * inverse_beta[c, d], 0.0), reliance[c, d], spread[c, d])
                v += noise[c, row, d]
                first += share[c] * mu
                second += share[c] * (v + mu * mu)
            mean[p, d] = first
            variance[p, d] = max(second - first * first, 0.0)
