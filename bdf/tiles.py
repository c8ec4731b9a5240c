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
overlap on an axis the tiles meet with a hard border there.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable, Mapping
from typing import Annotated, Literal, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from bdf import features
from bdf._validate import _bad_rows, as_noise_std, as_observations, as_points, as_sample_weight
from bdf.field import BayesianDynamicField, Posterior
from bdf.frames import ENUFrame
from bdf.grid import HingeGrid
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
        self.tile_grid(tuple(int(c) // 2 for c in n))  # an inner tile: raises if it has too many hinges
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
        lo, hi = self._grown(key)
        s = np.array(self.spacing_m)
        first = self.lower + np.floor((lo - self.lower) / s + 1e-9) * s
        last = self.lower + np.ceil((hi - self.lower) / s - 1e-9) * s
        return HingeGrid(first, last, s)

    def tile_field(self, key: TileKey) -> BayesianDynamicField:
        """An (unfitted) field with this tile's grid and the region's model settings."""
        grid = self.tile_grid(key)
        upper = grid.origin + grid.step * (np.array(grid.shape) - 1)
        return BayesianDynamicField(grid.origin, upper, grid.step, self.gamma, self.alpha, self.beta)

    def inside(self, X: np.ndarray) -> np.ndarray:
        """Rows of ``X`` (n, 3) inside the region's box (closed)."""
        return np.all((X >= self.lower) & (X <= self.upper), axis=1)

    def tiles_containing(self, X) -> dict[TileKey, np.ndarray]:
        """Row indices of ``X`` per tile whose grown box holds them (up to 8 tiles a point)."""
        return self._groups(self._inside_points(X))

    def _groups(self, X: np.ndarray) -> dict[TileKey, np.ndarray]:
        size, overlap, n = np.array(self.tile_size_m), np.array(self.overlap_m), np.array(self.tile_counts)
        home = np.clip(np.floor((X - self.lower) / size).astype(np.int64), 0, n - 1)
        per_axis = []  # per axis: (tile index, member) for the home tile and its two neighbours
        for d in range(3):
            options = []
            for step in (-1, 0, 1):
                i = home[:, d] + step
                lo = self.lower[d] + i * size[d]
                hi = np.minimum(lo + size[d], self.upper[d])
                member = (i >= 0) & (i < n[d]) & (X[:, d] >= lo - overlap[d]) & (X[:, d] <= hi + overlap[d])
                options.append((i, member))
            per_axis.append(options)
        keys, rows = [], []
        for (ix, mx), (iy, my), (iz, mz) in itertools.product(*per_axis):
            member = np.flatnonzero(mx & my & mz)
            keys.append(np.stack([ix[member], iy[member], iz[member]], axis=1))
            rows.append(member)
        keys, rows = np.concatenate(keys), np.concatenate(rows)
        unique, inverse = np.unique(keys, axis=0, return_inverse=True)
        order = np.argsort(inverse.ravel(), kind="stable")
        splits = np.split(rows[order], np.cumsum(np.bincount(inverse.ravel(), minlength=len(unique)))[:-1])
        return {tuple(int(v) for v in key): idx for key, idx in zip(unique, splits, strict=True)}

    def tile_weights(self, key: TileKey, X: np.ndarray) -> np.ndarray:
        """Unnormalised partition-of-unity weight of the tile at ``X`` (n,), see module doc."""
        return np.prod([self._axis_weight(key, d, X[:, d]) for d in range(3)], axis=0)

    def _axis_weight(self, key: TileKey, d: int, x: np.ndarray) -> np.ndarray:
        """The tile's weight along axis ``d`` (the weight is a product over axes)."""
        n, o, size = self.tile_counts[d], self.overlap_m[d], self.tile_size_m[d]
        lo = self.bounds_m.min[d] + key[d] * size
        hi = min(lo + size, self.bounds_m.max[d])
        w = np.ones(len(x))
        if o > 0:  # ramps only towards neighbours: the region's outer faces keep weight 1
            if key[d] > 0:
                w *= _ramp((x - lo + o) / (2 * o))
            if key[d] < n - 1:
                w *= _ramp((hi + o - x) / (2 * o))
        else:  # hard border: each point belongs to the tile whose core holds it
            home = np.clip(np.floor((x - self.lower[d]) / self.tile_size_m[d]), 0, n - 1)
            w *= home == key[d]
        return w

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
        noise = as_noise_std(input_noise_std, len(X))
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
                None if noise is None else noise[idx],
                None if weight is None else weight[idx],
            )
            out[key] = Increment(evidence, len(idx))
            if progress is not None:
                progress(done / len(groups))
        return out

    def posterior(self, key: TileKey, evidence: Evidence) -> Posterior:
        """The tile's posterior, with its variance density ready and its factors dropped."""
        return self.tile_field(key).set_evidence(evidence).posterior_.compact()

    def predict(
        self,
        X,
        posterior: Callable[[TileKey], Posterior | None] | Mapping[TileKey, Posterior],
        groups: dict[TileKey, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Blended predictive mean (n, 3), std (n, 3) and ``known`` (n,) at ``X``.

        ``posterior(key)`` gives a tile's posterior, or None for a tile without data, which
        answers with the prior (mean 0). ``known`` is False where only such tiles cover.
        ``groups``: :meth:`tiles_containing` of ``X`` if the caller already has it.
        """
        if isinstance(posterior, Mapping):
            posterior = posterior.get
        X = self._inside_points(X)
        parts, weight_sum = [], np.zeros(len(X))
        mean, known = np.zeros((len(X), 3)), np.zeros(len(X), bool)
        for key, idx in (self._groups(X) if groups is None else groups).items():
            w = self.tile_weights(key, X[idx])
            idx, w = idx[w > 0], w[w > 0]
            post = posterior(key)
            if post is None:
                mu, var = np.zeros((len(idx), 3)), self._prior_variance(key, X[idx])
            else:
                mu, std = post.predict(X[idx], return_std=True)
                var = std**2
                known[idx] = True
            mean[idx] += w[:, None] * mu
            weight_sum[idx] += w
            parts.append((idx, w, mu, var))
        mean /= weight_sum[:, None]
        var = np.zeros((len(X), 3))
        for idx, w, mu, v in parts:
            var[idx] += w[:, None] * (v + (mu - mean[idx]) ** 2)
        return mean, np.sqrt(var / weight_sum[:, None]), known

    def predict_grid(
        self, axes, posterior: Callable[[TileKey], Posterior | None] | Mapping[TileKey, Posterior]
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
                w = self._axis_weight(key, d, axes[d][idx])
                sel.append(idx[w > 0])
                w_axes.append(w[w > 0])
            if min(len(i) for i in sel) == 0:
                continue
            block = np.ix_(*sel)
            w = w_axes[0][:, None, None] * w_axes[1][None, :, None] * w_axes[2][None, None, :]
            sub = [axes[d][sel[d]] for d in range(3)]
            post = posterior(key)
            if post is None:
                mu, var = np.zeros((*w.shape, 3)), self._prior_variance(key, grid_axes=sub)
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


def _ramp(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)
