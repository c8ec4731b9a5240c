"""A region's evidence: points to per-tile, per-class increments, and their sum.

Each observation belongs to the tile whose core holds it (:func:`home_tiles`);
the tile's increment is what its core's points add to the region's evidence over the
tile's support (:func:`increments`, by :meth:`bdf.statistics.SectorEvidence.from_points`: the
one function everything that learns calls). Stored increments are decoded on the tile's
support (:func:`decode_tile`) and the region's evidence is their sum on the region's
lattice (:func:`region_total`), each observation counted once: tiles are independently
updatable, and the order of uploads does not matter.

Input noise widens a point's expected kernel (``1 + 2 gamma nu^2`` in its exponent); its
features are kept over the tile's support, so terms beyond the plain kernel's reach at
the cutoff are dropped (below ``cutoff^(1 / (1 + 2 gamma nu^2))``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import NamedTuple

import numpy as np

from bdf import features, sparse
from bdf.region.spec import RegionSpec, TileKey
from bdf.statistics import (
    ALT_BIN_M,
    FORMAT_VERSION,
    SPEED_BIN_MPS,
    SPEED_BINS,
    Evidence,
    SectorEvidence,
    altitude_bins,
)
from bdf.validation import as_noise_std, as_observations, as_sample_weight, take_rows


class Increment(NamedTuple):
    """What one upload adds to one tile."""

    evidence: Evidence
    points: int


def increments(
    spec: RegionSpec,
    X,
    V,
    *,
    input_noise_std=None,
    sample_weight=None,
    progress: Callable[[float], None] | None = None,
) -> dict[TileKey, Increment]:
    """The evidence each tile gains from observations ``(X, V)`` (all inside the region):
    its core's points, over its support.

    ``progress(fraction)`` is called after each tile (long fits report it).
    """
    X, V = as_observations(X, V)
    input_noise = as_noise_std(input_noise_std, len(X))
    weight = as_sample_weight(sample_weight, len(X))
    out = {}
    groups = home_tiles(spec, X)
    for done, (key, idx) in enumerate(groups.items(), start=1):
        grid = spec.tile_grid(key)
        rows = take_rows((X, V, input_noise, weight), idx)
        evidence = SectorEvidence.from_points(
            grid, spec.kernel, *rows, sectors=spec.sectors, noise_lattice=spec.tile_noise_lattice(key)
        )
        evidence.speeds = speed_histogram(grid, rows[0], rows[1])
        out[key] = Increment(evidence, len(idx))
        if progress is not None:
            progress(done / len(groups))
    return out


def speed_histogram(grid, X: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Rows per altitude bin over ``grid`` (:func:`bdf.statistics.altitude_bins`) and
    horizontal speed bin: additive, so the region knows how fast its traffic flies near each
    altitude (:func:`bdf.region.map.speed_bound`)."""
    first, count = altitude_bins(grid)
    alt = np.clip(np.floor(X[:, 2] / ALT_BIN_M).astype(np.int64) - first, 0, count - 1)
    speed = np.minimum(np.hypot(V[:, 0], V[:, 1]) // SPEED_BIN_MPS, SPEED_BINS - 1).astype(np.int64)
    counts = np.bincount(alt * SPEED_BINS + speed, minlength=count * SPEED_BINS)
    return counts.reshape(count, SPEED_BINS).astype(float)


def home_tiles(spec: RegionSpec, X) -> dict[TileKey, np.ndarray]:
    """Row indices of ``X`` per tile of ``spec`` whose core holds them (each row in one tile)."""
    X = spec.inside_points(X)
    if not len(X):
        return {}
    n = np.array(spec.tile_counts)
    flat = features.sort_key(features.cell_keys(X, spec.lower, np.array(spec.tile_size_m), n))
    order = np.argsort(flat, kind="stable")
    flat = flat[order]
    bounds = [0, *(np.flatnonzero(flat[1:] != flat[:-1]) + 1).tolist(), len(flat)]
    keys = np.stack(np.unravel_index(flat[bounds[:-1]], tuple(n)), axis=1).tolist()
    return {tuple(k): order[a:b] for a, b, k in zip(bounds[:-1], bounds[1:], keys, strict=True)}


def encode_tile(total: SectorEvidence, residual: SectorEvidence) -> bytes:
    """A tile's stored blob: its statistics and their rounding residual
    (:func:`bdf.statistics.compensated_sum`; format in :mod:`bdf.statistics`)."""
    first = total.to_bytes()
    return b"".join([np.array([len(first)], "<i8").tobytes(), first, residual.to_bytes()])


def decode_tile_parts(
    spec: RegionSpec, key: TileKey, blob: bytes, format_version: int = FORMAT_VERSION
) -> tuple[SectorEvidence, SectorEvidence | None]:
    """A tile's stored statistics and their rounding residual (None: stored before
    residuals were kept), each :meth:`SectorEvidence.to_bytes` on its support."""
    grid = spec.tile_grid(key)
    stencil = sparse.stencil_on(grid, spec.kernel)

    def part(data: bytes) -> SectorEvidence:
        lattice = spec.tile_noise_lattice(key)
        return SectorEvidence.from_bytes(data, grid, stencil, lattice, spec.sectors, format_version)

    if format_version < 5:
        return part(blob), None
    n = int(np.frombuffer(blob[:8], "<i8")[0]) if len(blob) >= 8 else -1
    if not 0 <= n <= len(blob) - 8:
        raise ValueError(f"a tile blob of {len(blob)} bytes does not hold its statistics and their residual")
    return part(blob[8 : 8 + n]), part(blob[8 + n :])


def decode_tile(
    spec: RegionSpec, key: TileKey, blob: bytes, format_version: int = FORMAT_VERSION
) -> SectorEvidence:
    """A tile's stored evidence: its statistics plus their rounding residual."""
    total, residual = decode_tile_parts(spec, key, blob, format_version)
    return total if residual is None else total + residual


def region_total(spec: RegionSpec, tiles: Mapping[TileKey, SectorEvidence]) -> SectorEvidence:
    """The region's evidence: the sum of its tiles', each placed on the region's lattice
    (the speed histogram too, where every tile has one: tiles stored before it have none)."""
    speeds = None
    if tiles and all(ev.speeds is not None for ev in tiles.values()):
        first, count = altitude_bins(spec.grid)
        speeds = np.zeros((count, SPEED_BINS))
        for key, ev in tiles.items():
            k0 = altitude_bins(spec.tile_grid(key))[0] - first
            speeds[k0 : k0 + len(ev.speeds)] += ev.speeds
    return SectorEvidence(
        tuple(
            _class_total(spec, {k: ev.classes[c] for k, ev in tiles.items()})
            for c in range(spec.sectors.classes)
        ),
        speeds,
    )


def _class_total(spec: RegionSpec, tiles: Mapping[TileKey, Evidence]) -> Evidence:
    """One class's :func:`region_total`."""
    total = Evidence.zeros(spec.grid, spec.noise_lattice)
    region_stencil = sparse.stencil_on(spec.grid, spec.kernel)
    for key, ev in tiles.items():
        grid = spec.tile_grid(key)
        i0 = np.round((grid.origin - spec.grid.origin) / spec.grid.step).astype(int)
        hinges = tuple(slice(a, a + n) for a, n in zip(i0, grid.shape, strict=True))
        mids = tuple(slice(2 * a, 2 * (a + n) - 1) for a, n in zip(i0, grid.shape, strict=True))
        total.density[mids] += ev.density
        total.proj.reshape(*spec.grid.shape, 3)[hinges] += ev.proj.reshape(*grid.shape, 3)
        total.mass.reshape(spec.grid.shape)[hinges] += ev.mass.reshape(grid.shape)
        total.count += ev.count
        total.v_sum += ev.v_sum
        total.v_sq += ev.v_sq
        if ev.moments is not None:
            sub = spec.tile_noise_lattice(key)
            j0 = np.round((sub.origin - spec.noise_lattice.origin) / sub.step).astype(int)
            cells = tuple(slice(a, a + n) for a, n in zip(j0, sub.shape, strict=True))
            total.moments[cells] += ev.moments
        if ev.gram_noisy is not None:
            if total.gram_noisy is None:
                total.gram_noisy = np.zeros((len(region_stencil.offsets), spec.grid.size))
            # the tile's stencil is the region's, cut where the support's edge is nearer
            tile_stencil = sparse.stencil_on(grid, spec.kernel)
            rows = {tuple(o): k for k, o in enumerate(region_stencil.offsets.tolist())}
            for k, o in enumerate(tile_stencil.offsets.tolist()):
                band = total.gram_noisy[rows[tuple(o)]].reshape(spec.grid.shape)
                band[hinges] += ev.gram_noisy[k].reshape(grid.shape)
    return total
