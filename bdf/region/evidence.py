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

from bdf import features, ingest, sparse
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
from bdf.validation import (
    as_noise_std,
    as_observations,
    as_sample_weight,
    noise_std_rows,
    rows_all,
    take_rows,
)

#: why a row is not learned from: every upload's ``rejected`` counts each, in this order
REJECTED = ("non_finite", "outside_region", "implausible_speed", "implausible_noise", "implausible_weight")
#: what an answer says of its accepted rows without a track id (their count: ``untracked``)
UNTRACKED_WARNING = (
    "rows without a track id (untracked) were counted as independent observations: samples of one "
    "track a second apart are not, and the map then trusts them far too much; send the columns "
    "track and t"
)


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
            grid, spec.kernel, *rows, sectors=spec.model_sectors, noise_lattice=spec.tile_noise_lattice(key)
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
    grid, lattice = spec.tile_grid(key), spec.tile_noise_lattice(key)
    stencil = sparse.stencil_on(grid, spec.kernel)

    def part(data: bytes) -> SectorEvidence:
        return SectorEvidence.from_bytes(data, grid, stencil, lattice, spec.model_sectors, format_version)

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
            for c in range(spec.model_sectors.classes)
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


def checked_rows(X, V, input_noise_std=None, sample_weight=None, track=None, time=None) -> tuple:
    """The rows as arrays of checked shapes: ``(X, V, noise, weight)``, and ``(track, time)``
    after them when given (so an upload without tracks keeps its digest)."""
    X, V = np.asarray(X, float), np.asarray(V, float)
    if X.ndim != 2 or X.shape[1] != 3 or V.shape != X.shape:
        raise ValueError(f"points and velocities must both be (n, 3), got {X.shape} and {V.shape}")
    noise = None if input_noise_std is None else noise_std_rows(input_noise_std, len(X))
    weight = None if sample_weight is None else np.asarray(sample_weight, float)
    if weight is not None and weight.shape != (len(X),):
        raise ValueError(f"sample_weight must have shape ({len(X)},), got {weight.shape}")
    if track is None and time is None:
        return X, V, noise, weight
    if track is None or time is None:
        raise ValueError("track and time go together: a track's rows are weighed by their times")
    track, time = np.asarray(track), np.asarray(time, float)
    if track.shape != (len(X),) or track.dtype.kind not in "iu" or time.shape != (len(X),):
        raise ValueError(
            f"track must be ({len(X)},) integer codes (bdf.ingest.track_codes) and time ({len(X)},) "
            f"seconds, got {track.dtype} {track.shape} and {time.shape}"
        )
    return X, V, noise, weight, track.astype(np.int64), time


def accepted_increments(
    spec: RegionSpec, X, V, input_noise_std=None, sample_weight=None, track=None, time=None, progress=None
) -> tuple[dict[TileKey, Increment], dict]:
    """The tile increments of observations, and the summary the ledger keeps: rows with a
    non-finite value, outside the region or outside its physical envelope (speeds, input
    noise, weights: :class:`bdf.region.spec.Envelope`) are rejected and counted by reason
    (:data:`REJECTED`), the rest accepted; the accepted rows of each track (``track`` codes
    >= 0, with ``time``) weighed by :func:`bdf.ingest.track_weights` (times their
    ``sample_weight``), the others counted as independent (``untracked``). Uploads, fits and
    Dask builds all learn through this."""
    rows = checked_rows(X, V, input_noise_std, sample_weight, track, time)
    return accepted_rows_increments(spec, *rows, progress=progress)


def accepted_rows_increments(spec: RegionSpec, X, V, noise, weight, track=None, time=None, *, progress=None):
    """:func:`accepted_increments` of arrays :func:`checked_rows` has passed."""
    keep, weight, counts, tracked = accepted_rows(spec, X, V, noise, weight, track, time)
    every = keep.all()

    def kept(a):  # compress: a tenth of a boolean index's time on (n, 3) rows
        return a if a is None or every else np.compress(keep, a, axis=0)

    tile_increments = (
        {}
        if not keep.any()
        else increments(
            spec,
            kept(X),
            kept(V),
            input_noise_std=kept(noise),
            sample_weight=kept(weight),
            progress=None if progress is None else (lambda f: progress(0.9 * f)),
        )
    )
    untracked = int((keep & ~tracked).sum())
    summary = {
        "accepted": int(keep.sum()),
        "rejected": {reason: int(c.sum()) for reason, c in zip(REJECTED, counts, strict=True)},
        "untracked": untracked,
    }
    if untracked:
        summary["warnings"] = [UNTRACKED_WARNING]
    return tile_increments, summary


def accepted_rows(spec: RegionSpec, X, V, noise, weight, track=None, time=None) -> tuple:
    """Which rows the region accepts (:func:`accepted_increments`), ``(keep, weight, counts,
    tracked)``: ``keep`` (n,), each row's likelihood weight (None: 1 each; the rows of a
    track weigh what they carry), the rejected rows per reason of :data:`REJECTED`, and
    which rows belong to a track."""
    finite = rows_all(np.isfinite(X)) & rows_all(np.isfinite(V))
    if noise is not None:
        finite &= rows_all(np.isfinite(noise))
    if weight is not None:
        finite &= np.isfinite(weight)
    tracked = np.zeros(len(X), bool)
    if track is not None:
        tracked = track >= 0
        finite &= ~tracked | np.isfinite(time)  # a track's row needs its time
    inside = finite & spec.inside(X)  # spec.inside is never true for a row that is not finite
    envelope = spec.envelope
    with np.errstate(invalid="ignore", over="ignore"):  # rows already rejected may hold NaN
        speed = inside & envelope.speed_ok(V)
        noise_ok = speed if noise is None else speed & envelope.noise_ok(noise)
        keep = noise_ok if weight is None else noise_ok & envelope.weight_ok(weight)
    if tracked.any():  # the kept rows of each track weigh what they carry
        on = np.where(keep, track, -1)  # rejected rows are no neighbours
        carried = ingest.track_weights(on, time, V, spec.gamma, max_interval_s=spec.track_interval_s)
        weight = carried if weight is None else weight * carried
    counts = (~finite, finite & ~inside, inside & ~speed, speed & ~noise_ok, noise_ok & ~keep)
    return keep, weight, counts, tracked
