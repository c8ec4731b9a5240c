"""Local separable Gaussian features on a regular lattice, evaluated block by block.

Everything the model computes is one of two sums over lattice points ``g`` with a
separable Gaussian weight ``w(x, g) = prod_d exp(-k_d (x_d - g_d)^2)``:

* :func:`splat`  ``T[g, c] = sum_n W[n, c] w(x_n, g)``   (data -> lattice)
* :func:`gather` ``out[n, c] = sum_g T[g, c] w(x_n, g)``  (lattice -> points)

with ``k = gamma`` on the hinge grid (features, ``Phi^T V``, the posterior mean) and
``k = 2 gamma`` on the midpoint grid (the data density behind ``Phi^T Phi`` and the
variance density). Points are grouped by blocks of lattice cells; all points of a block
share the same window of lattice points, so each block costs one dense BLAS product.

Kernel cutoff: a per-axis factor ``exp(-k_d (x_d - g_d)^2)`` below ``cutoff`` is zero
(the window half-width is ``sqrt(log(1 / cutoff) / k_d)``), in every path alike, so the
sums do not depend on how points are blocked or windows placed: a tile's support and the
region's lattice give the same terms at any cutoff. This is the only departure from the
dense formulas; tests/bdf/test_field.py compares with them to 1e-8 relative.
"""

from __future__ import annotations

import contextlib
from typing import NamedTuple

import numba
import numpy as np
from llvmlite import binding as llvm

from bdf._blas import single_threaded
from bdf.grid import Lattice
from bdf.kernel import DEFAULT_CUTOFF, window

#: Blocks grow (doubling) until they average this many points: fewer BLAS calls for sparse
#: data (radar scans), no wasted window for dense (Paris).
MIN_POINTS_PER_BLOCK = 32
#: Gathers of at most this many points run point by point, compiled; more share BLAS
#: products by blocks (``bench/bench_service.py``'s library rows, the demo's map: at 10,000
#: points 42.5 against 56.9 ms with 8 sectors, at 100,000 973.7 against 768.3 with 16).
POINTWISE_MAX_POINTS = 16384
#: The point-by-point gather sums a chunk of this many values of a table's rows (a lattice
#: column's z values and channels) side by side in registers (:func:`_gather_lanes`: two or
#: four AVX-512 vectors); which one a table uses: :func:`lanes_for`
LANE_WIDTHS = (16, 32)
#: ... for each of this many points at a time (neighbours), chunk by chunk
BLOCK_POINTS = 32
#: A chunk's plane of a point's window (its x-y columns times the chunk's values) is read
#: once per point of a block: at most this many bytes of it stay in L1 (48 KiB here) with
#: the rest of the kernel's data. At gamma = 1 / spacing^2, chunks of 32 values take
#: 0.69-0.91x the time of 16 on the hinge lattice (9 x 9 columns at the demo's cutoff, 11 x
#: 11 at the default: 21 and 31 KB) and 1.07-1.37x on its midpoints (13 x 13 and 15 x 15:
#: 43 and 58 KB), in five of six runs each (``bench/bench_kernels.py --parts lanes``)
L1_PLANE_BYTES = 32 * 1024
#: Points per BLAS call at most: its temporaries stay in cache (``bench/bench_build.py``).
CHUNK_POINTS = 2048
#: The same in a splat, whose operands are wider (``bench/bench_kernels.py``).
SPLAT_CHUNK = 256


def expected_kernel(gamma: np.ndarray, noise_std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-point coefficients of the expected kernel under Gaussian input noise.

    For ``x~ ~ N(x, nu^2)`` on one axis,
    ``E[exp(-g (x~ - h)^2)] = (1 + 2 g nu^2)^(-1/2) exp(-g (x - h)^2 / (1 + 2 g nu^2))``
    (paper section III-E; with ``nu = 0`` it is the plain kernel).

    Returns ``(k, amplitude)``: ``k`` is (n, 3), the amplitude (n,) is the product over axes.
    """
    spread = 1.0 + 2.0 * gamma * noise_std**2
    return gamma / spread, np.prod(spread, axis=1) ** -0.5


def _cut(factor: np.ndarray, cutoff: float) -> np.ndarray:
    """Per-axis factors below the cutoff set to zero (in place)."""
    factor[factor < cutoff] = 0.0
    return factor


@numba.njit(cache=True, nogil=True)
def _axis_factors(t, scale, reach, ratio, cutoff, d, out):  # pragma: no cover (compiled)
    """``out[j, p] = exp(-s_p (t_pd - j)^2)`` on axis ``d``, zero below ``cutoff`` or beyond
    ``reach``; ``t`` is (n, 3) in lattice steps, ``scale``, ``reach`` and
    ``ratio = exp(-2 scale)`` (1 or n, 3) as :func:`_per_scale` gives them, ``out`` (width, n).

    Two exponentials per point instead of one per lattice point: each value is the previous
    times a ratio, and each ratio the previous one times ``ratio`` (relative error ~ width x
    eps), points side by side so that the recurrence runs in SIMD lanes, each from its first
    lattice point within reach (a value >= ``cutoff``: no underflow; within reach a ratio is
    at most 1 / ``cutoff``: no overflow).
    """
    n = t.shape[0]
    # local arrays: the compiler then knows they do not overlap ``out``, and vectorises
    f, r, c, lo, hi = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    for p in range(n):
        q = min(p, scale.shape[0] - 1)
        s, ti = scale[q, d], t[p, d]
        a = max(np.ceil(ti - reach[q, d]), 0.0)
        lo[p], hi[p] = a, np.floor(ti + reach[q, d])
        f[p] = np.exp(-s * (ti - a) ** 2)
        r[p] = np.exp(-s * (2.0 * (a - ti) + 1.0))  # f(j + 1) = f(j) r(j), r(j + 1) = r(j) c
        c[p] = ratio[q, d]
    for j in range(out.shape[0]):
        row, at = out[j], float(j)
        for p in range(n):  # no branches
            v, on = f[p], at >= lo[p]
            row[p] = v if on & (at <= hi[p]) & (v >= cutoff) else 0.0
            f[p] = v * r[p] if on else v
            r[p] = r[p] * c[p] if on else r[p]
    return out


@numba.njit(cache=True, nogil=True)
def cell_keys(X, origin, size, shape):  # pragma: no cover (compiled)
    """The C-order index of the box of edge ``size`` from ``origin`` holding each point of
    ``X`` (n, 3), clipped to the ``shape`` boxes (one pass; numpy takes five)."""
    out = np.empty(X.shape[0], np.int64)
    for p in range(X.shape[0]):
        key = 0
        for d in range(3):
            c = min(max(np.floor((X[p, d] - origin[d]) / size[d]), 0.0), shape[d] - 1.0)
            key = key * shape[d] + int(c)
        out[p] = key
    return out


def sort_key(key: np.ndarray) -> np.ndarray:
    """Sort keys in 16 bits where they fit: numpy's stable sort is then a radix sort."""
    return key.astype(np.uint16) if len(key) and 0 <= key.min() and key.max() < 2**16 else key


@numba.njit(cache=True)
def _outer(a, b, out):  # pragma: no cover (compiled)
    """``out[i * q + j, n] = a[i, n] b[j, n]`` for ``a`` (p, n), ``b`` (q, n): per point,
    the outer product of its columns (points last, so the loops run long and in SIMD)."""
    p, n = a.shape
    q = b.shape[0]
    for i in range(p):
        for j in range(q):
            for m in range(n):
                out[i * q + j, m] = a[i, m] * b[j, m]
    return out


class _Blocks:
    """Points grouped by lattice-cell blocks, iterated in chunks with their window factors.

    ``order`` sorts the points by block (``slice(None)`` when there is one block).
    Iterating yields, per chunk of at most ``CHUNK_POINTS`` points of one block, the rows
    (into the sorted points), the block's window slices into the lattice array and the
    per-axis factors ``exp(-k (x - g)^2)`` (chunk, width[d]) at the window's lattice
    points g, zero below the cutoff. Chunks keep every temporary in cache: computed for
    all points at once they cost more in page faults than the products themselves.
    """

    def __init__(self, lattice: Lattice, X: np.ndarray, k: np.ndarray, cutoff: float, block: int):
        """``block``: the smallest block edge in lattice cells; it doubles while blocks are sparse."""
        k = np.asarray(k, float).reshape(-1, 3)  # one row for all points, or one each
        narrowest = k.min(axis=0)
        shape = np.array(lattice.shape)
        self.cutoff = cutoff
        reach = np.floor(window(narrowest, cutoff) / lattice.step).astype(int)
        if len(X) < 2 * MIN_POINTS_PER_BLOCK or np.all(2 * reach + 1 >= shape):
            # too few points to split, or every window would span the lattice (small tiles,
            # radar scans): one window over the whole lattice
            self.order, self.bounds, self.width = slice(None), [0, len(X)], shape
            self.start = np.zeros((1, 3), np.int64)
            self.t = (X - lattice.origin) / lattice.step
            self._scales(lattice, k)
            return
        self.order, self.bounds, self.start, self.width, self.t = _sort_blocks(
            X, lattice.origin, lattice.step, shape, reach, block, MIN_POINTS_PER_BLOCK
        )
        self._scales(lattice, k if len(k) == 1 else k[self.order])

    def _scales(self, lattice: Lattice, k: np.ndarray) -> None:
        """``k`` in lattice steps, and what the kernels take with it (:func:`_per_scale`)."""
        self.scale = k * lattice.step**2
        self.per_scale = _per_scale(self.scale, self.cutoff)

    def _factors(self, rows: slice) -> list[np.ndarray]:
        t, (scale, reach, ratio, cutoff) = self.t[rows], self.per_scale
        per = slice(None) if len(scale) == 1 else rows
        return [
            _axis_factors(
                t, scale[per], reach[per], ratio[per], cutoff, d, scratch(self._scratch[d], w, len(t))
            )
            for d, w in enumerate(self.width)
        ]

    def chunks(self):
        """Yield (rows into the sorted points, window slices into the lattice array)."""
        for s, a, b in zip(self.start, self.bounds[:-1], self.bounds[1:], strict=True):
            window = tuple(slice(s[d], s[d] + self.width[d]) for d in range(3))
            for c in range(a, b, CHUNK_POINTS):
                yield slice(c, min(c + CHUNK_POINTS, b)), window

    def __iter__(self):
        """Yield :meth:`chunks` with the chunk's factors fx, fy, fz, each (width[d], chunk)."""
        # one buffer per axis for all chunks: allocations of this size would each page-fault
        # where malloc returns freed memory to the system at once (Dask workers set that)
        self._scratch = [np.empty(int(w) * CHUNK_POINTS) for w in self.width]
        for rows, box in self.chunks():
            yield rows, box, *self._factors(rows)


@numba.njit(cache=True)
def _sort_blocks(X, origin, step, shape, reach, block, min_points):  # pragma: no cover (compiled)
    """The points ``X`` (n, 3) sorted by block of ``edge`` lattice cells (a stable counting
    sort, blocks in C order; points outside the lattice in the nearest cell or one beyond).
    The edge starts at ``block`` and doubles until the blocks average ``min_points`` points
    or it spans the lattice.

    Returns ``order``, the ``bounds`` of each block's run, each block's window ``start``
    (blocks, 3), the windows' ``width`` (3,) and the sorted points' positions ``t`` (n, 3)
    in lattice steps from their window's start. A block's window holds every lattice point
    within ``reach`` (steps, per axis) of its cells: a lattice point g can weigh >= cutoff
    for x in cells [c, c + e) only if c - r <= g <= c + e - 1 + r, a window of
    e + 2 r + 1. Shifted to lie inside the lattice, a window of the same width still holds
    all of those that exist, so no padding is needed and no window is wider than the
    lattice.
    """
    n = X.shape[0]
    cells = np.empty((n, 3), np.int64)
    for p in range(n):
        for d in range(3):
            cells[p, d] = int(min(max(np.floor((X[p, d] - origin[d]) / step[d]), -1.0), shape[d] - 1.0))
    n = cells.shape[0]
    while True:
        edge = np.minimum(block, shape)
        count = (shape - 1) // edge + 2  # blocks of cells -1 .. shape - 1, from -1
        counts = np.zeros(count[0] * count[1] * count[2] + 1, np.int64)
        key = np.empty(n, np.int64)
        for p in range(n):
            bx, by, bz = cells[p, 0] // edge[0] + 1, cells[p, 1] // edge[1] + 1, cells[p, 2] // edge[2] + 1
            key[p] = (bx * count[1] + by) * count[2] + bz
            counts[key[p] + 1] += 1
        used = np.count_nonzero(counts)
        if n >= min_points * used or block >= shape.max():
            break
        block *= 2
    first = np.cumsum(counts)  # first[b]: where block b's run starts
    order = np.empty(n, np.int64)
    fill = first[:-1].copy()
    for p in range(n):
        order[fill[key[p]]] = p
        fill[key[p]] += 1
    runs = np.flatnonzero(counts[1:])
    width = np.minimum(edge + 2 * reach + 1, shape)
    bounds = np.empty(len(runs) + 1, np.int64)
    start = np.empty((len(runs), 3), np.int64)
    for r in range(len(runs)):
        b = runs[r]
        bounds[r] = first[b]
        start[r, 0] = (b // (count[1] * count[2]) - 1) * edge[0]
        start[r, 1] = (b // count[2] % count[1] - 1) * edge[1]
        start[r, 2] = (b % count[2] - 1) * edge[2]
        for d in range(3):
            start[r, d] = min(max(start[r, d] - reach[d], 0), shape[d] - width[d])
    bounds[-1] = n
    t = np.empty((n, 3))
    for r in range(len(runs)):
        for q in range(bounds[r], bounds[r + 1]):
            for d in range(3):
                t[q, d] = (X[order[q], d] - origin[d]) / step[d] - start[r, d]
    return order, bounds, start, width, t


def scratch(buffer: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """A contiguous (rows, cols) view of the start of a flat buffer."""
    return buffer[: rows * cols].reshape(rows, cols)


@single_threaded
def splat(lattice: Lattice, X, W, k, *, cutoff=DEFAULT_CUTOFF, block=1) -> np.ndarray:
    """``T[g, c] = sum_n W[n, c] prod_d exp(-k_nd (x_nd - g_d)^2)``, shape lattice + (C,)."""
    n_out = W.shape[1]
    nx, ny, nz = lattice.shape
    # layout (x, c, y, z): the channels ride on the small x factor (_splat_blocks)
    out = np.zeros((nx, n_out, ny, nz))
    if len(X):
        blocks = _Blocks(lattice, X, k, cutoff, block)
        W = np.ascontiguousarray(np.asarray(W, float)[blocks.order])
        _splat_blocks(
            blocks.t, *blocks.per_scale, W, np.asarray(blocks.bounds), blocks.start, blocks.width, out
        )
    return np.ascontiguousarray(out.transpose(0, 2, 3, 1))


@numba.njit(cache=True, nogil=True)
def _splat_blocks(
    t, scale, reach, ratio, cutoff, W, bounds, start, width, out
):  # pragma: no cover (compiled)
    """``out`` (nx, C, ny, nz) += every block's sum: per chunk of at most
    :data:`SPLAT_CHUNK` points one GEMM (Ly Lz x n) @ (n x Lx C) of two matrices made from
    the points' window factors (:func:`_splat_rows`), added into the block's window. ``t``
    (n, 3) are the points' positions from their window's start (``start`` (blocks, 3)),
    sorted by block (``bounds``); the rest as :func:`_splat_rows` takes it."""
    C = W.shape[1]
    Lx, Ly, Lz = width[0], width[1], width[2]
    xc, yz = np.empty(SPLAT_CHUNK * Lx * C), np.empty(SPLAT_CHUNK * Ly * Lz)
    product = np.empty((Ly * Lz, Lx * C))
    for b in range(len(bounds) - 1):
        x0, y0, z0 = start[b, 0], start[b, 1], start[b, 2]
        for first in range(bounds[b], bounds[b + 1], SPLAT_CHUNK):
            last = min(first + SPLAT_CHUNK, bounds[b + 1])
            n = last - first
            per = slice(first, last) if scale.shape[0] > 1 else slice(0, 1)
            a, m = xc[: n * Lx * C].reshape((n, Lx * C)), yz[: n * Ly * Lz].reshape((Ly * Lz, n))
            _splat_rows(t[first:last], scale[per], reach[per], ratio[per], cutoff, W[first:last], width, a, m)
            np.dot(m, a, product)
            for i in range(Lx):
                for ch in range(C):
                    for j in range(Ly):
                        for k in range(Lz):
                            out[x0 + i, ch, y0 + j, z0 + k] += product[j * Lz + k, i * C + ch]


@numba.njit(cache=True, nogil=True)
def _splat_rows(t, scale, reach, ratio, cutoff, W, width, xc, yz):  # pragma: no cover (compiled)
    """The GEMM operands of a chunk of points ``p``: ``xc[p, i C + c] = fx_i W[p, c]``, and
    ``yz[j Lz + k, p] = fy_j fz_k`` points last (vectorised over the points; the fastest
    layout of the larger operand and its product), from the window factors
    (:func:`_axis_factors`; ``t`` (n, 3) in steps from the window's start, ``scale``,
    ``reach`` and ``ratio`` (1 or n, 3) as :func:`_per_scale` gives them, ``width`` the
    window's (Lx, Ly, Lz))."""
    n, C = W.shape
    Lx, Ly, Lz = width[0], width[1], width[2]
    fx = _axis_factors(t, scale, reach, ratio, cutoff, 0, np.empty((Lx, n)))
    fy = _axis_factors(t, scale, reach, ratio, cutoff, 1, np.empty((Ly, n)))
    fz = _axis_factors(t, scale, reach, ratio, cutoff, 2, np.empty((Lz, n)))
    for p in range(n):
        for i in range(Lx):
            for ch in range(C):
                xc[p, i * C + ch] = fx[i, p] * W[p, ch]
    for j in range(Ly):
        for k in range(Lz):
            row, a, b = yz[j * Lz + k], fy[j], fz[k]
            for p in range(n):
                row[p] = a[p] * b[p]
    return xc, yz


def lanes_for(lattice: Lattice, k, cutoff: float) -> int:
    """The chunk width (:data:`LANE_WIDTHS`) of a :class:`LaneTable` on ``lattice`` that is
    gathered with ``k`` (3,; or per point, (n, 3): the widest window counts): the widest
    whose plane of a point's window fits :data:`L1_PLANE_BYTES` (the hinge lattice at
    ``gamma = 1 / spacing^2`` and the default cutoff: 11 x 11 columns, 32 values; its
    midpoint lattice, whose window has twice the columns: 16)."""
    k = np.asarray(k, float).reshape(-1, 3).min(axis=0)
    reach = window(k * lattice.step**2, cutoff)[:2]
    columns = np.prod(np.minimum(2 * np.floor(reach) + 1, lattice.shape[:2]))
    fits = [w for w in LANE_WIDTHS if columns * w * 8 <= L1_PLANE_BYTES]
    return max(fits, default=LANE_WIDTHS[0])


class LaneTable(NamedTuple):
    """Lattice values (nx, ny, nz, C) as :func:`_gather_lanes` reads them: each row (a
    lattice column's z values and channels, nz C values) cut in chunks of ``lanes`` values
    (one of :data:`LANE_WIDTHS`), the last padded with zeros, chunk first: ``values``
    (chunks, nx, ny, lanes). A chunk of a window's rows is then contiguous along y; in an
    (nx, ny, nz C) table each row's chunk lies nz C values from the next, a cache miss per
    row on tables of many channels."""

    values: np.ndarray
    layers: int
    channels: int

    @classmethod
    def of(cls, T, lanes: int) -> LaneTable:
        if lanes not in LANE_WIDTHS:
            raise ValueError(f"a lane table's chunks hold one of {LANE_WIDTHS} values, not {lanes}")
        T = np.asarray(T, float)
        nx, ny, nz, C = T.shape
        chunks = -(-nz * C // lanes)
        rows = np.zeros((nx, ny, chunks * lanes))
        rows[..., : nz * C] = T.reshape(nx, ny, nz * C)
        return cls(np.ascontiguousarray(rows.reshape(nx, ny, chunks, lanes).transpose(2, 0, 1, 3)), nz, C)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """(nx, ny, nz, C), as the lattice values'."""
        return (*self.values.shape[1:3], self.layers, self.channels)

    def array(self) -> np.ndarray:
        """The lattice values (nx, ny, nz, C)."""
        nx, ny, nz, C = self.shape
        rows = self.values.transpose(1, 2, 0, 3).reshape(nx, ny, -1)
        return rows[..., : nz * C].reshape(nx, ny, nz, C)

    @property
    def nbytes(self) -> int:
        return self.values.nbytes


def gather(lattice: Lattice, X, T, k, *, cutoff=DEFAULT_CUTOFF, block=1) -> np.ndarray:
    """``out[n, c] = sum_g T[g, c] prod_d exp(-k_d (x_nd - g_d)^2)``, shape (N, C).

    Each point is summed over its own window by a compiled kernel (:func:`gather_pointwise`)
    when the points are few (:data:`POINTWISE_MAX_POINTS`); more share windows and BLAS
    products by blocks (:func:`gather_blocked`), which reuse the table's values across
    points. ``T``: lattice values (nx, ny, nz, C) or their :class:`LaneTable`."""
    if len(X) <= POINTWISE_MAX_POINTS:
        return gather_pointwise(lattice, X, T, k, cutoff=cutoff)
    return gather_blocked(lattice, X, T, k, cutoff=cutoff, block=block)


@single_threaded
def gather_blocked(lattice: Lattice, X, T, k, *, cutoff=DEFAULT_CUTOFF, block=1) -> np.ndarray:
    """:func:`gather` by blocks of points and BLAS products (the reference path)."""
    T = T.array() if isinstance(T, LaneTable) else T
    n_out = T.shape[-1]
    out = np.empty((len(X), n_out))
    if len(X) == 0:
        return out
    blocks = _Blocks(lattice, X, k, cutoff, block)
    T = gather_table(T)
    sorted_out = np.empty_like(out)
    yz = np.empty(int(blocks.width[1] * blocks.width[2]) * CHUNK_POINTS)
    for rows, (wx, wy, wz), fx, fy, fz in blocks:
        product = _outer(fy, fz, scratch(yz, len(fy) * len(fz), rows.stop - rows.start))
        sorted_out[rows] = contract(fx.T, product.T, T[wy, wz, wx])
    out[blocks.order] = sorted_out
    return out


def gather_table(T) -> np.ndarray:
    """Lattice values (nx, ny, nz, C) in the layout :func:`contract` reads: (ny, nz, nx, C)."""
    return np.ascontiguousarray(np.asarray(T).transpose(1, 2, 0, 3))


def contract(fx, yz, table) -> np.ndarray:
    """``out[n, c] = sum_ijk fx[n, i] fy[n, j] fz[n, k] T[i, j, k, c]`` for the x factors
    ``fx`` (n, Lx), the y-z factor products ``yz`` (n, Ly, Lz) and ``table`` =
    :func:`gather_table` of ``T``: one GEMM (n x Ly*Lz) @ (Ly*Lz x Lx*C) and one product
    with the x factors."""
    Ly, Lz, Lx, n_out = table.shape
    txc = (yz.reshape(-1, Ly * Lz) @ table.reshape(Ly * Lz, Lx * n_out)).reshape(-1, Lx, n_out)
    return np.einsum("nxc,nx->nc", txc, fx)


def gather_grid(lattice: Lattice, axes, T, k, *, cutoff=DEFAULT_CUTOFF) -> np.ndarray:
    """:func:`gather` at every point of the grid ``axes[0] x axes[1] x axes[2]``, shape
    (nx, ny, nz, C). The weight is separable, so this is three small contractions with
    per-axis kernel matrices instead of one product per point. ``T``: lattice values
    (nx, ny, nz, C) or their :class:`LaneTable`, contracted as it lies over x and y, then
    cut back into z and channels (copying it back costs more per slab of a grid in the
    service than the contraction)."""
    k = np.broadcast_to(np.asarray(k, float), (3,))
    K = [
        _cut(np.exp(-k[d] * (np.asarray(axes[d], float)[:, None] - lattice.axis(d)[None, :]) ** 2), cutoff)
        for d in range(3)
    ]
    if not isinstance(T, LaneTable):
        return np.einsum("xi,yj,zk,ijkc->xyzc", *K, np.asarray(T), optimize="optimal")
    Kx, Ky, Kz = K
    chunks, nx, ny, lanes = T.values.shape
    by_x = np.matmul(Kx, T.values.reshape(chunks, nx, ny * lanes)).reshape(chunks, len(Kx), ny, lanes)
    rows = np.tensordot(Ky, by_x, axes=(1, 2)).transpose(2, 0, 1, 3)  # (x, y, chunks, lanes)
    rows = rows.reshape(len(Kx), len(Ky), -1)[..., : T.layers * T.channels]
    rows = rows.reshape(len(Kx), len(Ky), T.layers, T.channels).transpose(3, 0, 1, 2)
    # each channel's grid contiguous, as the einsum lays it out (what follows reads by class)
    return np.matmul(np.ascontiguousarray(rows), Kz.T).transpose(1, 2, 3, 0)


@single_threaded
def gram_band(lattice: Lattice, X, k, amplitude, stencil, *, cutoff=DEFAULT_CUTOFF) -> np.ndarray:
    """``sum_n a_n^2 phi(x_n) phi(x_n)^T`` on ``stencil``'s pairs, as its band (K, M), with
    per-point widths ``k``.

    Used where the midpoint identity does not hold (noisy inputs: ``k`` differs per
    point). Costs O(N W^2) with W the hinges per window; meant for radar-sized batches.
    """
    M = lattice.size
    out = np.zeros((len(stencil.offsets), M))
    if len(X) == 0:
        return out
    blocks = _Blocks(lattice, X, k, cutoff, block=1)
    amplitude = amplitude[blocks.order]
    flat = np.arange(M).reshape(lattice.shape)
    width = tuple(int(w) for w in blocks.width)
    local = np.arange(int(np.prod(width))).reshape(width)
    for rows, box, fx, fy, fz in blocks:
        phi = fx.T[:, :, None, None] * fy.T[:, None, :, None] * fz.T[:, None, None, :]
        phi = phi.reshape(len(phi), -1) * amplitude[rows, None]
        pairs = phi.T @ phi
        hinges = flat[box]
        for k, o in enumerate(stencil.offsets):
            sel = tuple(slice(max(0, -o[d]), width[d] - max(0, o[d])) for d in range(3))
            if any(s.start >= s.stop for s in sel):
                continue
            a = local[sel].ravel()
            b = a + (o[0] * width[1] + o[1]) * width[2] + o[2]
            out[k, hinges[sel].ravel()] += pairs[a, b]
    return out


@numba.njit(cache=True, nogil=True)
def _window_exponents(X, origin, step, scale, reach, shape, log_cutoff):  # pragma: no cover (compiled)
    """The points ``X`` (n, 3) by lattice cell (C order; outside: the nearest cell), so that
    neighbours find most of their window in cache: that ``order`` (n,), then in that order
    each point's window on each axis, its first lattice point ``lo`` and count ``width``
    (n, 3), and the exponents ``-s (t - lo - j)^2`` of its factors (n, 3, W): ``-inf``
    beyond the window or below ``log_cutoff`` (the factor is zero). ``t`` is the point in
    lattice steps, ``scale`` (1 or n, 3, in ``X``'s order) the kernel in steps^-2,
    ``reach`` its windows' half-width."""
    n = X.shape[0]
    t, key = np.empty((n, 3)), np.empty(n, np.int64)
    for p in range(n):
        c = 0
        for d in range(3):
            t[p, d] = (X[p, d] - origin[d]) / step[d]
            c = c * shape[d] + min(max(int(np.floor(t[p, d])), 0), shape[d] - 1)
        key[p] = c
    order = np.argsort(key)
    widest = 1
    for q in range(reach.shape[0]):
        for d in range(3):
            widest = max(widest, min(int(2.0 * reach[q, d]) + 1, shape[d]))
    lo, width = np.empty((n, 3), np.int64), np.empty((n, 3), np.int64)
    out = np.empty((n, 3, widest))
    for p in range(n):
        q = min(order[p], scale.shape[0] - 1)
        for d in range(3):
            s, ti = scale[q, d], t[order[p], d]
            a = min(max(np.ceil(ti - reach[q, d]), 0.0), float(shape[d]))
            b = min(max(np.floor(ti + reach[q, d]), -1.0), shape[d] - 1.0)
            lo[p, d], width[p, d] = int(a), max(int(b - a) + 1, 0)
            for j in range(widest):
                e = -s * (ti - a - j) ** 2
                out[p, d, j] = e if (j < width[p, d]) & (e >= log_cutoff) else -np.inf
    return order, lo, width, out


def _point_windows(lattice: Lattice, X, scale, cutoff) -> tuple[np.ndarray, ...]:
    """The points ``X`` (n, 3) in lattice-cell order (``order``), and in that order each
    one's window (``lo``, ``width``: (n, 3)) and its per-axis factors (n, 3, W), zero below
    the cutoff and beyond the window: the exponentials in one numpy call, which evaluates
    them side by side in SIMD lanes where a compiled loop calls the scalar ``exp`` for each
    (queries' server CPU: ``bench/RESULTS.md``, 2026-11-29); the rest in one compiled call
    (numpy's steps on a 1,000-point query cost as much as the exponentials)."""
    order, lo, width, factors = _window_exponents(
        X, lattice.origin, lattice.step, scale, window(scale, cutoff), np.array(lattice.shape), np.log(cutoff)
    )
    return order, lo, width, np.exp(factors, out=factors)


@numba.njit(cache=True, nogil=True)
def _sum_z(factors, width, row, first, out):  # pragma: no cover (compiled)
    """``out[c] = sum_k fz_k row[first + k C + c]``: the last axis of a window's sum."""
    C = len(out)
    for c in range(C):
        total = 0.0
        for k in range(width[2]):
            total += factors[2, k] * row[first + k * C + c]
        out[c] = total


@numba.njit(inline="always")
def _chunk_16(flat, at, stride, fx, fy, wx, wy, acc, q):  # pragma: no cover (compiled)
    """One chunk of 16 values of a window's rows (:func:`_gather_lanes`): summed over ``wy``
    columns from ``flat[at]`` along y, then over ``wx`` x steps of ``stride``, into
    ``acc[q:q + 16]``; the sums in scalars that the SLP vectoriser keeps in registers."""
    b0 = b1 = b2 = b3 = b4 = b5 = b6 = b7 = b8 = b9 = b10 = b11 = b12 = b13 = b14 = b15 = 0.0
    for i in range(wx):
        a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = a11 = a12 = a13 = a14 = a15 = 0.0
        col = at + np.uint64(i) * stride
        for j in range(wy):
            fj = fy[j]
            a0 += fj * flat[col + np.uint64(0)]
            a1 += fj * flat[col + np.uint64(1)]
            a2 += fj * flat[col + np.uint64(2)]
            a3 += fj * flat[col + np.uint64(3)]
            a4 += fj * flat[col + np.uint64(4)]
            a5 += fj * flat[col + np.uint64(5)]
            a6 += fj * flat[col + np.uint64(6)]
            a7 += fj * flat[col + np.uint64(7)]
            a8 += fj * flat[col + np.uint64(8)]
            a9 += fj * flat[col + np.uint64(9)]
            a10 += fj * flat[col + np.uint64(10)]
            a11 += fj * flat[col + np.uint64(11)]
            a12 += fj * flat[col + np.uint64(12)]
            a13 += fj * flat[col + np.uint64(13)]
            a14 += fj * flat[col + np.uint64(14)]
            a15 += fj * flat[col + np.uint64(15)]
            col += np.uint64(16)
        fi = fx[i]
        b0 += fi * a0
        b1 += fi * a1
        b2 += fi * a2
        b3 += fi * a3
        b4 += fi * a4
        b5 += fi * a5
        b6 += fi * a6
        b7 += fi * a7
        b8 += fi * a8
        b9 += fi * a9
        b10 += fi * a10
        b11 += fi * a11
        b12 += fi * a12
        b13 += fi * a13
        b14 += fi * a14
        b15 += fi * a15
    acc[q + 0], acc[q + 1], acc[q + 2], acc[q + 3] = b0, b1, b2, b3
    acc[q + 4], acc[q + 5], acc[q + 6], acc[q + 7] = b4, b5, b6, b7
    acc[q + 8], acc[q + 9], acc[q + 10], acc[q + 11] = b8, b9, b10, b11
    acc[q + 12], acc[q + 13], acc[q + 14], acc[q + 15] = b12, b13, b14, b15


@numba.njit(inline="always")
def _chunk_32(flat, at, stride, fx, fy, wx, wy, acc, q):  # pragma: no cover (compiled)
    """One chunk of 32 values of a window's rows (:func:`_gather_lanes`): summed over ``wy``
    columns from ``flat[at]`` along y, then over ``wx`` x steps of ``stride``, into
    ``acc[q:q + 32]``; the sums in scalars that the SLP vectoriser keeps in registers."""
    b0 = b1 = b2 = b3 = b4 = b5 = b6 = b7 = b8 = b9 = b10 = b11 = b12 = b13 = b14 = b15 = 0.0
    b16 = b17 = b18 = b19 = b20 = b21 = b22 = b23 = b24 = b25 = b26 = b27 = b28 = b29 = b30 = b31 = 0.0
    for i in range(wx):
        a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = a11 = a12 = a13 = a14 = a15 = 0.0
        a16 = a17 = a18 = a19 = a20 = a21 = a22 = a23 = a24 = a25 = a26 = a27 = a28 = a29 = a30 = a31 = 0.0
        col = at + np.uint64(i) * stride
        for j in range(wy):
            fj = fy[j]
            a0 += fj * flat[col + np.uint64(0)]
            a1 += fj * flat[col + np.uint64(1)]
            a2 += fj * flat[col + np.uint64(2)]
            a3 += fj * flat[col + np.uint64(3)]
            a4 += fj * flat[col + np.uint64(4)]
            a5 += fj * flat[col + np.uint64(5)]
            a6 += fj * flat[col + np.uint64(6)]
            a7 += fj * flat[col + np.uint64(7)]
            a8 += fj * flat[col + np.uint64(8)]
            a9 += fj * flat[col + np.uint64(9)]
            a10 += fj * flat[col + np.uint64(10)]
            a11 += fj * flat[col + np.uint64(11)]
            a12 += fj * flat[col + np.uint64(12)]
            a13 += fj * flat[col + np.uint64(13)]
            a14 += fj * flat[col + np.uint64(14)]
            a15 += fj * flat[col + np.uint64(15)]
            a16 += fj * flat[col + np.uint64(16)]
            a17 += fj * flat[col + np.uint64(17)]
            a18 += fj * flat[col + np.uint64(18)]
            a19 += fj * flat[col + np.uint64(19)]
            a20 += fj * flat[col + np.uint64(20)]
            a21 += fj * flat[col + np.uint64(21)]
            a22 += fj * flat[col + np.uint64(22)]
            a23 += fj * flat[col + np.uint64(23)]
            a24 += fj * flat[col + np.uint64(24)]
            a25 += fj * flat[col + np.uint64(25)]
            a26 += fj * flat[col + np.uint64(26)]
            a27 += fj * flat[col + np.uint64(27)]
            a28 += fj * flat[col + np.uint64(28)]
            a29 += fj * flat[col + np.uint64(29)]
            a30 += fj * flat[col + np.uint64(30)]
            a31 += fj * flat[col + np.uint64(31)]
            col += np.uint64(32)
        fi = fx[i]
        b0 += fi * a0
        b1 += fi * a1
        b2 += fi * a2
        b3 += fi * a3
        b4 += fi * a4
        b5 += fi * a5
        b6 += fi * a6
        b7 += fi * a7
        b8 += fi * a8
        b9 += fi * a9
        b10 += fi * a10
        b11 += fi * a11
        b12 += fi * a12
        b13 += fi * a13
        b14 += fi * a14
        b15 += fi * a15
        b16 += fi * a16
        b17 += fi * a17
        b18 += fi * a18
        b19 += fi * a19
        b20 += fi * a20
        b21 += fi * a21
        b22 += fi * a22
        b23 += fi * a23
        b24 += fi * a24
        b25 += fi * a25
        b26 += fi * a26
        b27 += fi * a27
        b28 += fi * a28
        b29 += fi * a29
        b30 += fi * a30
        b31 += fi * a31
    acc[q + 0], acc[q + 1], acc[q + 2], acc[q + 3] = b0, b1, b2, b3
    acc[q + 4], acc[q + 5], acc[q + 6], acc[q + 7] = b4, b5, b6, b7
    acc[q + 8], acc[q + 9], acc[q + 10], acc[q + 11] = b8, b9, b10, b11
    acc[q + 12], acc[q + 13], acc[q + 14], acc[q + 15] = b12, b13, b14, b15
    acc[q + 16], acc[q + 17], acc[q + 18], acc[q + 19] = b16, b17, b18, b19
    acc[q + 20], acc[q + 21], acc[q + 22], acc[q + 23] = b20, b21, b22, b23
    acc[q + 24], acc[q + 25], acc[q + 26], acc[q + 27] = b24, b25, b26, b27
    acc[q + 28], acc[q + 29], acc[q + 30], acc[q + 31] = b28, b29, b30, b31


def _gather_lanes(order, lo, width, factors, table, channels, out):  # pragma: no cover (compiled)
    """:func:`gather` point by point: ``out[order[p], c] = sum_ijk fx fy fz T[i, j, k, c]``
    over each point's own window (:func:`_point_windows`: the points' ``order``, then in
    it ``lo`` and ``width`` (n, 3) and the factors (n, 3, W)), ``table`` a
    :class:`LaneTable`'s values. Points go by blocks of
    :data:`BLOCK_POINTS` (neighbours, in lattice-cell order): each chunk of the window's
    rows is summed for every point of the block before the next chunk (:func:`_chunk_16`,
    :func:`_chunk_32`), so the chunk's plane of the window is read from L1, not L2
    (:func:`lanes_for`). Then z (:func:`_sum_z`). Flat indices are unsigned: no
    negative-index wraparound between the loads."""
    chunks, nx, ny, lanes = table.shape
    flat = table.reshape(-1)
    stride = np.uint64(ny * lanes)  # one x step in ``flat``
    span = np.empty((BLOCK_POINTS, 2), np.int64)  # the chunks a point's window rows cover
    acc = np.zeros((BLOCK_POINTS, chunks * lanes))  # by position in the row
    for start in range(0, lo.shape[0], BLOCK_POINTS):
        m = min(BLOCK_POINTS, lo.shape[0] - start)
        first, end = chunks, 0
        for b in range(m):
            p = start + b
            span[b, 0] = span[b, 1] = 0
            if width[p, 0] > 0 and width[p, 1] > 0 and width[p, 2] > 0:
                span[b, 0] = lo[p, 2] * channels // lanes
                span[b, 1] = ((lo[p, 2] + width[p, 2]) * channels + lanes - 1) // lanes
                first, end = min(first, span[b, 0]), max(end, span[b, 1])
        for chunk in range(first, end):
            for b in range(m):
                if span[b, 0] <= chunk < span[b, 1]:
                    p = start + b
                    at = np.uint64(((chunk * nx + lo[p, 0]) * ny + lo[p, 1]) * lanes)
                    fx, fy, wx, wy = factors[p, 0], factors[p, 1], width[p, 0], width[p, 1]
                    if lanes == 32:
                        _chunk_32(flat, at, stride, fx, fy, wx, wy, acc[b], chunk * lanes)
                    else:
                        _chunk_16(flat, at, stride, fx, fy, wx, wy, acc[b], chunk * lanes)
        for b in range(m):
            p = start + b
            if span[b, 1] > span[b, 0]:
                _sum_z(factors[p], width[p], acc[b], lo[p, 2] * channels, out[order[p]])
            else:
                out[order[p]] = 0.0
    return out


@contextlib.contextmanager
def _slp_vectorised():
    """Compile with LLVM's SLP vectoriser, which numba leaves off by default (numba#8705:
    miscompilations elsewhere), and let it build vectors of 512 bits (LLVM builds 256 on
    AVX-512 machines unless told; on others the backend splits them): what is compiled with
    it is tested equal to the BLAS path and to the dense sums (tests/bdf/test_features.py).
    The LLVM option is process-wide, but only this vectoriser reads it, and numba runs it
    nowhere else."""
    llvm.set_option("bdf", "-slp-max-reg-size=512")
    before, numba.config.SLP_VECTORIZE = numba.config.SLP_VECTORIZE, 1
    try:
        yield
    finally:
        numba.config.SLP_VECTORIZE = before


with _slp_vectorised():  # compiled (or loaded from numba's cache) now, in one thread
    _gather_lanes = numba.njit(
        "f8[:, ::1](i8[::1], i8[:, ::1], i8[:, ::1], f8[:, :, ::1], f8[:, :, :, ::1], i8, f8[:, ::1])",
        cache=True,
        nogil=True,
        fastmath={"contract"},  # fused multiply-adds: one rounding per term, not two
    )(_gather_lanes)


def gather_pointwise(lattice: Lattice, X, T, k, *, cutoff=DEFAULT_CUTOFF) -> np.ndarray:
    """:func:`gather` compiled point by point (each point's own window): the fast path of
    queries. Equal to :func:`gather_blocked` to rounding
    (tests/bdf/test_features.py). ``T``: lattice values (nx, ny, nz, C), or the
    :class:`LaneTable` of them that a posterior keeps. Points are visited by lattice cell,
    so neighbours find most of their window in cache."""
    table = T if isinstance(T, LaneTable) else LaneTable.of(T, lanes_for(lattice, k, cutoff))
    X = np.ascontiguousarray(X, float)
    out = np.empty((len(X), table.channels))
    if len(X) == 0:
        return out
    scale = np.ascontiguousarray(np.asarray(k, float).reshape(-1, 3) * lattice.step**2)
    return _gather_lanes(*_point_windows(lattice, X, scale, cutoff), table.values, table.channels, out)


def _per_scale(scale, cutoff) -> tuple:
    """What the point-by-point kernels take per ``scale`` (1 or n, 3): it, the window's
    half-width ``reach``, ``ratio = exp(-2 scale)``, and the cutoff."""
    scale = np.ascontiguousarray(scale)
    return scale, window(scale, cutoff), np.exp(-2.0 * scale), float(cutoff)
