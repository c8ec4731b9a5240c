"""Regions split into tiles: each tile is one field, learned and stored on its own,
queried as one seamless map.

A region's ENU box is cut into tiles of ``tile_size_m``; tile ``(i, j, k)`` has the *core*
box ``bounds.min + (i, j, k) * tile_size`` (the last tile per axis ends at ``bounds.max``).
Its field covers the core grown by ``overlap_m`` on every side; its hinges sit on the
region-wide lattice ``bounds.min + n * spacing`` (the grown box is widened to the next
lattice points), so neighbouring tiles share hinges where they overlap. An observation
updates every tile whose grown box holds it, so neighbours see the same data near their
border.

A query blends the tiles covering a point with a partition of unity: along each axis a
tile's weight rises from 0 at ``core_min - overlap`` to 1 at ``core_min + overlap`` with
the C2 ramp ``s(t) = 6t^5 - 15t^4 + 10t^3`` (and falls likewise at the top). Since
``s(t) + s(1 - t) = 1`` the weights of neighbours sum to one, and since each tile's mean is
smooth where its weight is non-zero, the blended mean is continuous (C2) across borders.
The variance is the mixture variance ``sum_t w_t (var_t + (mean_t - mean)^2)``. With zero
overlap on an axis the tiles meet with a hard border there. With ``noise_spacing_m`` each
tile's noise term is local (:mod:`bdf.noise`), its moments stored with its evidence.

A tile without data answers with mean 0 and, with ``alpha="auto"``, the region's
climatology as its variance: the weighted mean square of every velocity the region has
seen (:meth:`RegionSpec.empty_variance`). An auto prior has nothing to be fitted on there,
and the paper's fixed values (``EMPTY_ALPHA``, ``EMPTY_BETA``) are on the scale of
normalised data: on real traffic they claim less uncertainty than observed airspace has.
With a fixed ``alpha`` the model's own prior answers.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable, Mapping
from typing import Annotated, Literal, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from bdf import features, noise
from bdf._blas import single_threaded
from bdf._validate import _bad_rows, as_noise_std, as_observations, as_points, as_sample_weight
from bdf.field import BayesianDynamicField, Posterior
from bdf.frames import ENUFrame
from bdf.grid import HingeGrid, Lattice
from bdf.stats import Evidence
from bdf.tuning import EMPTY_ALPHA, EMPTY_BETA

TileKey = tuple[int, int, int]
#: Most tiles a region may have (keys, ledgers and listings stay small).
MAX_TILES = 100_000

Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
PositiveVec3 = Annotated[list[Positive], Field(min_length=3, max_length=3)]
Hyper = Literal["auto"] | Positive | PositiveVec3


class Origin(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    lat: Annotated[float, Field(ge=-90, le=90)]
    lon: Annotated[float, Field(ge=-180, le=180)]
    alt_m: Finite = 0.0


class Bounds(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    min: Vec3
    max: Vec3

    @model_validator(mode="after")
    def _ordered(self):
        if any(hi <= lo for lo, hi in zip(self.min, self.max, strict=True)):
            raise ValueError(f"bounds_m.max {self.max} must exceed bounds_m.min {self.min} on every axis")
        return self


class Increment(NamedTuple):
    """What one upload adds to one tile."""

    evidence: Evidence
    points: int


class RegionSpec(BaseModel):
    """A named city region: geodetic origin, ENU box, tiling and model settings (metres, 1/m^2).

    Its JSON form (``model_dump(mode="json")``) is the body ``POST /v1/regions`` accepts.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    name: Annotated[str, Field(pattern=r"^[a-z0-9][a-z0-9_-]{0,62}$")]
    origin: Origin
    bounds_m: Bounds
    tile_size_m: PositiveVec3
    overlap_m: Annotated[list[NonNegative], Field(min_length=3, max_length=3)] = [0.0, 0.0, 0.0]
    spacing_m: PositiveVec3
    gamma: PositiveVec3
    alpha: Hyper = "auto"
    beta: Hyper = "auto"
    noise_spacing_m: PositiveVec3 | None = None
    noise_prior: Positive = 0.1

    @model_validator(mode="after")
    def _consistent(self):
        size, overlap = np.array(self.tile_size_m), np.array(self.overlap_m)
        if np.any(2 * overlap > size):
            raise ValueError(
                f"overlap_m {self.overlap_m} must be at most half of tile_size_m {self.tile_size_m}"
            )
        n = self.tile_counts
        if int(np.prod(n)) > MAX_TILES:
            raise ValueError(f"{int(np.prod(n))} tiles ({n} per axis) is more than {MAX_TILES}")
        inner = tuple(int(c) // 2 for c in n)
        self.tile_grid(inner)  # raises if a tile would have too many hinges
        self.tile_noise_lattice(inner)  # or too many noise lattice points
        return self

    # -- geometry ---------------------------------------------------------------------------
    @property
    def lower(self) -> np.ndarray:
        return np.array(self.bounds_m.min, float)

    @property
    def upper(self) -> np.ndarray:
        return np.array(self.bounds_m.max, float)

    @functools.cached_property  # a tuple: equality of specs still compares fields only
    def tile_counts(self) -> tuple[int, int, int]:
        n = np.ceil((self.upper - self.lower) / np.array(self.tile_size_m) - 1e-9).astype(int)
        return tuple(int(c) for c in np.maximum(n, 1))

    def frame(self) -> ENUFrame:
        return _frame(self.origin.lat, self.origin.lon, self.origin.alt_m)

    def core(self, key: TileKey) -> tuple[np.ndarray, np.ndarray]:
        """The tile's own box (without overlap)."""
        lo = self.lower + np.array(key) * np.array(self.tile_size_m)
        return lo, np.minimum(lo + self.tile_size_m, self.upper)

    def _grown(self, key: TileKey) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.core(key)
        return lo - self.overlap_m, hi + np.array(self.overlap_m)

    def tile_grid(self, key: TileKey) -> HingeGrid:
        """Hinges of the tile: the grown box widened to the region-wide hinge lattice."""
        _, hi = self._grown(key)
        s = np.array(self.spacing_m)
        last = self.lower + np.ceil((hi - self.lower) / s - 1e-9) * s
        return HingeGrid(self._grid_origins(np.array([key]))[0], last, s)

    def tile_noise_lattice(self, key: TileKey) -> Lattice | None:
        """The tile's local-noise lattice (its field's), or None with the global noise."""
        if self.noise_spacing_m is None:
            return None
        grid = self.tile_grid(key)
        return noise.noise_lattice(grid.origin, _last_hinge(grid), self.noise_spacing_m)

    def _grid_origins(self, keys: np.ndarray) -> np.ndarray:
        """First hinge of the tiles ``keys`` (n, 3): the grown box's low corner, widened."""
        s = np.array(self.spacing_m)
        lo = self.lower + keys * np.array(self.tile_size_m) - self.overlap_m
        return self.lower + np.floor((lo - self.lower) / s + 1e-9) * s

    def tile_field(self, key: TileKey) -> BayesianDynamicField:
        """An (unfitted) field with this tile's grid and the region's model settings."""
        grid = self.tile_grid(key)
        return BayesianDynamicField(
            grid.origin,
            _last_hinge(grid),
            grid.step,
            self.gamma,
            self.alpha,
            self.beta,
            noise_spacing=self.noise_spacing_m,
            noise_prior=self.noise_prior,
        )

    def inside(self, X: np.ndarray) -> np.ndarray:
        """Rows of ``X`` (n, 3) inside the region's box (closed)."""
        return np.all((X >= self.lower) & (X <= self.upper), axis=1)

    def tiles_containing(self, X) -> dict[TileKey, np.ndarray]:
        """Row indices of ``X`` per tile whose grown box holds them (up to 8 tiles a point)."""
        rows, keys = self._memberships(self._inside_points(X))
        return {key: rows[a:b] for a, b, key in _runs(keys)}

    def _memberships(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each (row of ``X``, tile whose grown box holds it): rows (P,) and tile keys (P, 3),
        sorted by tile, then row."""
        size, overlap, n = np.array(self.tile_size_m), np.array(self.overlap_m), np.array(self.tile_counts)
        home = np.clip(np.floor((X - self.lower) / size).astype(np.int64), 0, n - 1)
        # per axis, the home tile and its two neighbours, and whether the point is in each
        index = home[:, None, :] + np.array([-1, 0, 1])[:, None]  # (n, 3 options, 3 axes)
        lo = self.lower + index * size
        hi = np.minimum(lo + size, self.upper)
        x = X[:, None, :]
        member = (index >= 0) & (index < n) & (x >= lo - overlap) & (x <= hi + overlap)
        both = member[:, :, None, None, 0] & member[:, None, :, None, 1] & member[:, None, None, :, 2]
        rows, ox, oy, oz = np.nonzero(both)
        keys = np.stack([index[rows, ox, 0], index[rows, oy, 1], index[rows, oz, 2]], axis=1)
        order = np.lexsort((rows, keys[:, 2], keys[:, 1], keys[:, 0]))
        return rows[order], keys[order]

    def tile_weights(self, key: TileKey, X: np.ndarray) -> np.ndarray:
        """Unnormalised partition-of-unity weight of the tile at ``X`` (n,), see module doc."""
        return self._weights(np.broadcast_to(np.asarray(key), X.shape), X)

    def _weights(self, keys: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Weight of tile ``keys[i]`` at ``X[i]`` (keys and X both (n, 3))."""
        return np.prod([self._axis_weight(d, keys[:, d], X[:, d]) for d in range(3)], axis=0)

    def _axis_weight(self, d: int, index, x: np.ndarray) -> np.ndarray:
        """The weight along axis ``d`` of tile(s) ``index`` (the weight is a product over axes)."""
        n, o, size = self.tile_counts[d], self.overlap_m[d], self.tile_size_m[d]
        lo = self.bounds_m.min[d] + np.asarray(index) * size
        hi = np.minimum(lo + size, self.bounds_m.max[d])
        if o == 0:  # hard border: each point belongs to the tile whose core holds it
            home = np.clip(np.floor((x - self.lower[d]) / size), 0, n - 1)
            return (home == index).astype(float)
        # ramps only towards neighbours: the region's outer faces keep weight 1
        rise = np.where(index > 0, _ramp((x - lo + o) / (2 * o)), 1.0)
        return rise * np.where(index < n - 1, _ramp((hi + o - x) / (2 * o)), 1.0)

    def _inside_points(self, X) -> np.ndarray:
        X = as_points(X, "X", allow_empty=True)
        outside = ~self.inside(X)
        if outside.any():
            raise ValueError(f"points outside region {self.name!r} bounds: {_bad_rows(outside)}")
        return X

    # -- learning and querying -------------------------------------------------------------
    def increments(
        self,
        X,
        V,
        *,
        input_noise_std=None,
        sample_weight=None,
        progress: Callable[[float], None] | None = None,
    ) -> dict[TileKey, Increment]:
        """The evidence each tile gains from observations ``(X, V)`` (all inside the region).

        ``progress(fraction)`` is called after each tile (long fits report it).
        """
        X, V = as_observations(X, V)
        input_noise = as_noise_std(input_noise_std, len(X))
        weight = as_sample_weight(sample_weight, len(X))
        gamma = np.array(self.gamma)
        out = {}
        groups = self.tiles_containing(X)
        for done, (key, idx) in enumerate(groups.items(), start=1):
            evidence = Evidence.from_points(
                self.tile_grid(key),
                gamma,
                X[idx],
                V[idx],
                None if input_noise is None else input_noise[idx],
                None if weight is None else weight[idx],
                noise_lattice=self.tile_noise_lattice(key),
            )
            out[key] = Increment(evidence, len(idx))
            if progress is not None:
                progress(done / len(groups))
        return out

    def empty_variance(self, count: float, v_sq) -> np.ndarray | None:
        """The predictive variance (3,) of a tile without data, from the region's totals
        (``count``: sum of sample weights, ``v_sq``: sum of weighted squared velocities, over
        its tiles): the climatology ``v_sq / count`` with ``alpha="auto"``; None (the model's
        prior) with a fixed alpha or before any data."""
        if self.alpha != "auto" or not count > 0:
            return None
        return np.asarray(v_sq, float) / count

    def posterior(self, key: TileKey, evidence: Evidence) -> Posterior:
        """The tile's posterior, with its variance density ready and its factors dropped."""
        return self.tile_field(key).set_evidence(evidence).posterior_.compact()

    @single_threaded
    def predict(
        self,
        X,
        posterior: Callable[[TileKey], Posterior | None] | Mapping[TileKey, Posterior],
        groups: dict[TileKey, np.ndarray] | None = None,
        empty_variance: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Blended predictive mean (n, 3), std (n, 3) and ``known`` (n,) at ``X``.

        ``posterior(key)`` gives a tile's posterior, or None for a tile without data, which
        answers with mean 0 and variance ``empty_variance`` (:meth:`empty_variance`; None:
        the model's prior). ``known`` is False where only such tiles cover.
        ``groups``: :meth:`tiles_containing` of ``X`` if the caller already has it.

        All (point, tile) pairs are evaluated in one batch: the kernel factors of every
        pair come from a few vectorised calls (tiles share the region's hinge lattice, so
        only their origins differ), then each tile costs two small GEMMs
        (:func:`features.contract`) on its weights and variance density (and, with local
        noise, one gather on its noise lattice).
        """
        if isinstance(posterior, Mapping):
            posterior = posterior.get
        X = self._inside_points(X)
        if groups is None:
            rows, keys = self._memberships(X)
        else:
            rows = np.concatenate([np.zeros(0, np.int64), *groups.values()])
            keys = np.repeat(
                np.array(list(groups), np.int64).reshape(-1, 3), [len(r) for r in groups.values()], axis=0
            )
        points = X[rows]
        w = self._weights(keys, points)
        rows, keys, w, points = rows[w > 0], keys[w > 0], w[w > 0], points[w > 0]
        tiles = _runs(keys)
        posts = [posterior(key) for _, _, key in tiles]
        shapes = [
            self.tile_grid(key).shape if p is None else p.grid.shape
            for (*_, key), p in zip(tiles, posts, strict=True)
        ]
        shape = np.max([(1, 1, 1), *shapes], axis=0)
        # per-axis kernel factors of every pair, on the hinge and the midpoint lattice
        t = (points - self._grid_origins(keys)) / np.array(self.spacing_m)  # in hinge steps
        gamma_steps = np.array(self.gamma) * np.array(self.spacing_m) ** 2
        hinge = [np.exp(-gamma_steps[d] * (t[:, d, None] - np.arange(shape[d])) ** 2) for d in range(3)]
        half = [
            np.exp(-gamma_steps[d] / 2 * (2 * t[:, d, None] - np.arange(2 * shape[d] - 1)) ** 2)
            for d in range(3)
        ]
        hinge_yz = hinge[1][:, :, None] * hinge[2][:, None, :]
        half_yz = half[1][:, :, None] * half[2][:, None, :]
        mu, var = np.zeros((len(rows), 3)), np.empty((len(rows), 3))
        beta = np.empty((len(rows), 3))  # noise precision of each pair's tile, NaN: no data
        scatter = np.empty((len(rows), 3))  # noise variance of each pair with data
        for (a, b, key), post in zip(tiles, posts, strict=True):
            if post is None:
                var[a:b] = (
                    self._prior_variance(key, points[a:b]) if empty_variance is None else empty_variance
                )
                beta[a:b] = np.nan
                continue
            mean_table, var_table = post.gather_tables()
            nx, ny, nz = post.grid.shape
            mu[a:b] = features.contract(hinge[0][a:b, :nx], hinge_yz[a:b, :ny, :nz], mean_table)
            var[a:b] = features.contract(
                half[0][a:b, : 2 * nx - 1], half_yz[a:b, : 2 * ny - 1, : 2 * nz - 1], var_table
            )
            beta[a:b] = post.beta
            scatter[a:b] = post.noise_variance(points[a:b], mu[a:b])
        known = ~np.isnan(beta[:, 0])
        var[known] = np.maximum(var[known] / beta[known], 0.0) + scatter[known]
        # partition-of-unity blend: weighted mean, mixture variance
        n = len(X)
        weight_sum = np.bincount(rows, w, n)
        mean = np.stack([np.bincount(rows, w * mu[:, c], n) for c in range(3)], axis=1) / weight_sum[:, None]
        spread = w[:, None] * (var + (mu - mean[rows]) ** 2)
        var = np.stack([np.bincount(rows, spread[:, c], n) for c in range(3)], axis=1) / weight_sum[:, None]
        return mean, np.sqrt(var), np.bincount(rows, known, n) > 0

    def predict_grid(
        self,
        axes,
        posterior: Callable[[TileKey], Posterior | None] | Mapping[TileKey, Posterior],
        empty_variance: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`predict` on the grid ``axes[0] x axes[1] x axes[2]`` (inside the region):
        mean and std (nx, ny, nz, 3), known (nx, ny, nz). Kernels and blending weights are
        separable, so each tile costs a few small contractions on its part of the grid."""
        if isinstance(posterior, Mapping):
            posterior = posterior.get
        axes = [np.asarray(a, float).ravel() for a in axes]
        for d, a in enumerate(axes):
            if (
                len(a) == 0
                or not np.all(np.isfinite(a))
                or a.min() < self.lower[d]
                or a.max() > self.upper[d]
            ):
                raise ValueError(f"grid axis {d} must be finite, non-empty and inside region {self.name!r}")
        shape = tuple(len(a) for a in axes)
        mean, weight_sum, known = np.zeros((*shape, 3)), np.zeros(shape), np.zeros(shape, bool)
        parts = []
        for key in self.tiles_overlapping([a.min() for a in axes], [a.max() for a in axes]):
            lo, hi = self._grown(key)
            sel, w_axes = [], []
            for d in range(3):
                idx = np.flatnonzero((axes[d] >= lo[d]) & (axes[d] <= hi[d]))
                w = self._axis_weight(d, key[d], axes[d][idx])
                sel.append(idx[w > 0])
                w_axes.append(w[w > 0])
            if min(len(i) for i in sel) == 0:
                continue
            block = np.ix_(*sel)
            w = w_axes[0][:, None, None] * w_axes[1][None, :, None] * w_axes[2][None, None, :]
            sub = [axes[d][sel[d]] for d in range(3)]
            post = posterior(key)
            if post is None:
                mu = np.zeros((*w.shape, 3))
                if empty_variance is None:
                    var = self._prior_variance(key, grid_axes=sub)
                else:
                    var = np.broadcast_to(np.asarray(empty_variance, float), mu.shape)
            else:
                mu, var = post.predict_grid(sub)
                known[block] = True
            mean[block] += w[..., None] * mu
            weight_sum[block] += w
            parts.append((block, w, mu, var))
        mean /= weight_sum[..., None]
        var = np.zeros((*shape, 3))
        for block, w, mu, v in parts:
            var[block] += w[..., None] * (v + (mu - mean[block]) ** 2)
        return mean, np.sqrt(var / weight_sum[..., None]), known

    def tiles_overlapping(self, lo, hi) -> list[TileKey]:
        """Keys of the tiles whose grown box meets the box ``lo .. hi``."""
        size, overlap, n = np.array(self.tile_size_m), np.array(self.overlap_m), np.array(self.tile_counts)
        first = np.clip(np.floor((np.asarray(lo) - overlap - self.lower) / size).astype(int), 0, n - 1)
        last = np.clip(np.floor((np.asarray(hi) + overlap - self.lower) / size).astype(int), 0, n - 1)
        return list(itertools.product(*(range(int(a), int(b) + 1) for a, b in zip(first, last, strict=True))))

    def _prior_variance(self, key: TileKey, X: np.ndarray | None = None, grid_axes=None) -> np.ndarray:
        """``1/beta + phi^T phi / alpha`` per component: a tile that has seen nothing (at
        points ``X``, or on the grid ``grid_axes``)."""
        alpha = EMPTY_ALPHA if self.alpha == "auto" else np.broadcast_to(np.asarray(self.alpha), (3,))
        beta = EMPTY_BETA if self.beta == "auto" else np.broadcast_to(np.asarray(self.beta), (3,))
        grid = self.tile_grid(key)
        ones, k = np.ones((*grid.shape, 1)), 2.0 * np.array(self.gamma)
        if grid_axes is None:
            norm = features.gather(grid, X, ones, k)
        else:
            norm = features.gather_grid(grid, grid_axes, ones, k)
        return norm / alpha + 1.0 / beta


@functools.lru_cache(maxsize=64)
def _frame(lat: float, lon: float, alt_m: float) -> ENUFrame:
    """Frames are shared per origin: building a pyproj transformer costs milliseconds."""
    return ENUFrame(lat, lon, alt_m)


def key_str(key: TileKey) -> str:
    """Tile key as stored and shown: ``"i_j_k"``."""
    return "_".join(str(int(v)) for v in key)


def parse_key(text: str) -> TileKey:
    parts = text.split("_")
    if len(parts) != 3 or not all(p.lstrip("-").isdigit() for p in parts):
        raise ValueError(f"a tile key is three integers joined by '_', got {text!r}")
    return tuple(int(p) for p in parts)


def _last_hinge(grid: HingeGrid) -> np.ndarray:
    return grid.origin + grid.step * (np.array(grid.shape) - 1)


def _ramp(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)


def _runs(keys: np.ndarray) -> list[tuple[int, int, TileKey]]:
    """Runs of equal rows of the sorted ``keys`` (n, 3): (start, stop, key) each."""
    starts = np.flatnonzero(np.any(keys[1:] != keys[:-1], axis=1)) + 1
    bounds = [0, *starts.tolist(), len(keys)] if len(keys) else []
    firsts = keys[bounds[:-1]].tolist()  # Python ints, one conversion for all runs
    return [(a, b, tuple(k)) for (a, b), k in zip(itertools.pairwise(bounds), firsts, strict=True)]
