"""The precision's sparse algebra: stencil, supernodal factorisation, selected inversion.

Two hinges couple through ``c(h_m - h_m') = exp(-sum_d gamma_d (h_md - h_m'd)^2 / 2)``
(:mod:`bdf.stats`), so pairs whose factor is below the kernel ``cutoff`` are dropped:
the precision is a 3-D *stencil* (the offsets ``o`` with ``c(o) >= cutoff``) around every
hinge. Matrices on that pattern are kept as *bands*: ``band[k, m] = A[m, m + o_k]`` for
the half of the offsets that is lexicographically >= 0 (the other half by symmetry),
zeros where ``m + o_k`` leaves the lattice.

A band is factored in a geometric nested dissection of the lattice (:func:`dissection`:
less fill than METIS, in a tenth of its time), by supernodes: a symbolic analysis of the
pattern (:func:`_symbolic`: the elimination tree, its postorder and CHOLMOD's relaxed
supernodes) gives the layout of the supernodes' dense blocks, and the factorisation
(:func:`_factor`), the solves and the selected inversion are each one compiled call on
those blocks with LAPACK and BLAS (:mod:`bdf._lapack`) that releases the GIL, so that the
classes of a directional map are analysed and factored side by side. The factor gives
the log-determinant (evidence) and the solves (posterior mean). Only the hinges the data
touch are factored (:class:`Support`): a hinge whose Gram diagonal is zero has a zero row
(``G`` is positive semi-definite), so ``G + shift I`` is ``shift`` there, apart from the
rest. Sparse traffic on a large lattice, and each heading sector of a directional map,
touch a fraction of the hinges: the factor's work falls roughly with its cube. Where a
class touches most of the hinges its total touches, it is factored on the total's support
instead (:data:`COVER`): one analysis serves them all.
The variance density needs the posterior covariance only on the stencil's pairs, which
lie in the factor's pattern: :func:`_selected_inverse` computes the inverse on that pattern
by the Takahashi recursions, supernode by supernode.
"""

from __future__ import annotations

import functools
import threading
from typing import NamedTuple

import numba
import numpy as np
import scipy.sparse as sp

from bdf import _lapack
from bdf.grid import Lattice

#: A band is factored on a kept support with up to this many times its own hinges
#: (:meth:`Stencil.support`): exact either way (the extra hinges are decoupled).
COVER = 1.25


class NotPositiveDefinite(ValueError):
    """The precision lost positive definiteness (a bad fixed alpha or beta)."""


@functools.lru_cache(maxsize=16)
def stencil(shape: tuple[int, int, int], step: tuple, gamma: tuple, cutoff: float) -> Stencil:
    """The pattern of a lattice's precision: cached per lattice and kernel."""
    return Stencil(shape, np.array(step), np.array(gamma), cutoff)


class Stencil:
    """Offsets ``o`` (hinge steps) with ``c(o) >= cutoff``: the half kept in bands
    (``offsets``, lexicographically >= 0, zero first), and a nested-dissection order of the
    lattice (:func:`dissection`)."""

    #: Supports kept per stencil: a directional map's classes use the total's, or their own
    #: where they touch fewer hinges (:data:`COVER`); refits find them all here.
    SUPPORTS = 4

    def __init__(self, shape, step, gamma, cutoff):
        self._key = (tuple(shape), tuple(step.tolist()), tuple(gamma.tolist()), float(cutoff))
        self.shape, self.cutoff = tuple(shape), float(cutoff)
        steps = gamma * step**2 / 2.0  # exponent per squared hinge step, per axis
        limit = np.log(1.0 / cutoff)
        self.reach = np.minimum(np.floor(np.sqrt(limit / steps)).astype(int), np.array(shape) - 1)
        axes = [np.arange(-r, r + 1) for r in self.reach]
        o = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        o = o[(o**2 @ steps) <= limit]
        half = (o[:, 0] > 0) | ((o[:, 0] == 0) & ((o[:, 1] > 0) | ((o[:, 1] == 0) & (o[:, 2] >= 0))))
        o = o[half]
        self.offsets = o[np.lexsort((o[:, 2], o[:, 1], o[:, 0]))]
        self.factor = np.exp(-(self.offsets**2 @ steps))  # c(o)
        self._lock = threading.RLock()  # the lazy parts build on one another
        self._order = None
        self._supports: dict[bytes, Support] = {}

    def __reduce__(self):
        """Pickled as its key: unpickled, it is the cached stencil of that process (posteriors
        computed in another process arrive without their factors, see RegionMaps)."""
        return stencil, self._key

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def valid(self, k: int) -> tuple[slice, slice, slice]:
        """Slices of the hinges ``m`` whose partner ``m + o_k`` is on the lattice."""
        o = self.offsets[k]
        return tuple(slice(max(0, -o[d]), self.shape[d] - max(0, o[d])) for d in range(3))

    def pairs(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices of the hinges ``m`` of :meth:`valid` and of their partners ``m + o_k``."""
        o = self.offsets[k]
        m = np.arange(self.size).reshape(self.shape)[self.valid(k)].ravel()
        return m, m + (o[0] * self.shape[1] + o[1]) * self.shape[2] + o[2]

    @property
    def order(self) -> np.ndarray:
        """The hinges (flat indices) in the order the matrices use: :func:`dissection`."""
        with self._lock:
            if self._order is None:
                self._order = dissection(self.shape, self.reach)
            return self._order

    def support(self, active: np.ndarray) -> Support:
        """A :class:`Support` holding the hinges ``active`` (M,) bool: a kept one (the last
        :attr:`SUPPORTS`: a search factors one support many times) that holds them and at
        most :data:`COVER` times as many (the classes of a map within their total's: one
        analysis serves them all), else their own."""
        active = np.asarray(active, bool)
        order = self.order
        with self._lock:
            count = int(active.sum())
            found = next(
                (
                    s
                    for s in reversed(self._supports.values())
                    if len(s.order) <= COVER * count and not np.any(active & ~s.active)
                ),
                None,
            ) or Support(self, active, order)
            key = np.packbits(found.active).tobytes()
            self._supports.pop(key, None)
            self._supports[key] = found  # the most recent last
            while len(self._supports) > self.SUPPORTS:
                self._supports.pop(next(iter(self._supports)))
            return found

    def factor_of(self, band: np.ndarray, shift: float) -> Factor:
        """The factor of ``band + shift I`` on the hinges the band touches (nonzero diagonal)."""
        return self.support(np.asarray(band[0]) != 0).factor_of(band, shift)


class Support:
    """The hinges a band touches (``active``) and what their factorisation needs: the lower
    triangle of their pattern as CSC in the stencil's order restricted to them, and the
    layout of the factor's blocks (:class:`_Layout`), analysed at the first factorisation.
    The other hinges are decoupled: ``shift`` alone."""

    def __init__(self, stencil: Stencil, active: np.ndarray, order: np.ndarray):
        self.stencil, self.active = stencil, np.asarray(active, bool)
        if len(stencil.offsets) * stencil.size >= 2**31:  # the entries' indices are 32-bit
            raise ValueError(
                f"a lattice of {stencil.size} hinges is too large for a stencil of {len(stencil.offsets)}"
            )
        self.order = order[self.active[order]]  # active hinges, in the dissection's order
        rank = np.full(stencil.size, -1, np.int64)
        rank[self.order] = np.arange(len(self.order))
        self._indptr, self._rows, self._source = _lower_pattern(
            np.array(stencil.shape), stencil.offsets, rank
        )
        self._lock = threading.Lock()
        self.layout = None

    def matrix(self, band: np.ndarray) -> sp.csc_matrix:
        """The lower triangle of ``band``'s matrix on the active hinges, in :attr:`order`."""
        n = len(self.order)
        values = np.asarray(band).ravel()[self._source]
        return sp.csc_matrix((values, self._rows, self._indptr), shape=(n, n))

    def factor_of(self, band: np.ndarray, shift: float) -> Factor:
        """The factor of ``band``'s matrix on the active hinges ``+ shift I`` (with ``shift``
        on the rest): the matrix placed in the blocks, factored in place (:func:`_factor`)."""
        if not len(self.order):
            return Factor(self, None, shift)
        with self._lock:
            if self.layout is None:
                self.layout = _analyse(self._indptr, self._rows)
        lay = self.layout
        blocks = np.zeros(lay.offsets[-1])  # fresh pages come zeroed
        failed = _factor_of(lay, np.ascontiguousarray(band, float).ravel(), self._source, shift, blocks)
        if failed:
            raise NotPositiveDefinite(f"the factorisation broke down at supernode {failed - 1}")
        return Factor(self, blocks, shift)


class _Layout(NamedTuple):
    """The factor's supernodes: their first columns (then the column count), rows (each
    one's sorted, its own columns first: ``rows[rowptr[s]:rowptr[s + 1]]``) and block
    offsets (its rows by its columns, column-major, one after another); each column's
    supernode and diagonal entry; the support's hinges in the factor's column order; per
    entry of the support's matrix, its place in the blocks."""

    starts: np.ndarray
    rowptr: np.ndarray
    rows: np.ndarray
    offsets: np.ndarray
    column_node: np.ndarray
    diagonal: np.ndarray
    columns: np.ndarray
    position: np.ndarray

    def column_counts(self) -> np.ndarray:
        """Entries of each column of L, its diagonal included (padding of the relaxed
        supernodes included: what the kernels compute)."""
        heights = np.diff(self.rowptr)[self.column_node]
        return heights - (np.arange(len(self.column_node)) - self.starts[self.column_node])


def _analyse(indptr: np.ndarray, rows: np.ndarray) -> _Layout:
    """The layout of the factors of a lower pattern (CSC, sorted, diagonal included;
    :func:`_symbolic`), and where each entry of the pattern goes in the blocks."""
    columns, starts, rowptr, srows = _symbolic(indptr, rows)
    widths, heights = np.diff(starts), np.diff(rowptr)
    offsets = np.concatenate([[0], np.cumsum(heights * widths)])
    column_node = np.repeat(np.arange(len(widths)), widths)
    within = np.arange(len(column_node)) - starts[column_node]
    diagonal = offsets[column_node] + within * (heights[column_node] + 1)
    if offsets[-1] >= 2**31:  # the entries' places are 32-bit
        raise ValueError(f"the factor needs {offsets[-1] * 8 / 2**30:.0f} GiB: a coarser lattice or cutoff")
    position = _block_positions(indptr, rows, columns, starts, rowptr, srows, offsets)
    return _Layout(starts, rowptr, srows, offsets, column_node, diagonal, columns, position)


class Factor:
    """One factorisation ``P (A + shift I) P^T = L L^T`` of a support's matrix ``A`` (in its
    order; ``P`` only postorders it), as the blocks of its supernodes (:class:`_Layout`);
    ``shift`` alone on the other hinges."""

    def __init__(self, support: Support, blocks, shift: float):
        self.support, self._blocks, self.shift = support, blocks, float(shift)

    @property
    def stencil(self) -> Stencil:
        return self.support.stencil

    def logdet(self) -> float:
        idle = (self.stencil.size - len(self.support.order)) * np.log(self.shift)
        if self._blocks is None:
            return idle
        return idle + 2.0 * float(np.sum(np.log(self._blocks[self.support.layout.diagonal])))

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``(A + shift I)^-1 b`` for ``b`` (M, ...) in the lattice's flat order."""
        x = np.asarray(b, float) / self.shift
        if self._blocks is not None:
            lay = self.support.layout
            hinges = self.support.order[lay.columns]
            y = np.ascontiguousarray(np.asarray(b, float)[hinges].reshape(len(hinges), -1))
            _solve(lay.rowptr, lay.rows, lay.starts, lay.offsets, self._blocks, y)
            x[hinges] = y.reshape((len(hinges), *x.shape[1:]))
        return x

    @property
    def nbytes(self) -> int:
        return self._blocks.nbytes if self._blocks is not None else 0

    @property
    def madds(self) -> float:
        """Multiply-adds of the factorisation (:func:`factor_madds`)."""
        return factor_madds(self.support.layout.column_counts())

    @property
    def inverse_madds(self) -> float:
        """Multiply-adds of :meth:`inverse_band`'s dense steps, per supernode of ``w`` columns
        and ``r`` rows below them: ``S_RR Y`` (r^2 w), ``Y^T S_RJ`` (w^2 r), the inverse of
        the diagonal block (w^3 / 3) and ``Y`` (r w^2 / 2)."""
        layout = self.support.layout
        w = np.diff(layout.starts).astype(float)
        r = np.diff(layout.rowptr) - w
        return float(np.sum(r * r * w + w * w * r + w**3 / 3 + r * w * w / 2))

    def inverse_band(self) -> np.ndarray:
        """The inverse on the stencil, as a band (len(offsets), M): selected inversion on the
        active hinges, ``1 / shift`` on the diagonal of the others."""
        st = self.stencil
        band = np.zeros(len(st.offsets) * st.size)
        band[: st.size] = 1.0 / self.shift
        if self._blocks is not None:
            blocks = self._blocks.copy()  # numpy's: huge pages for the kernels' gathers
            info = _inverse_band(self.support.layout, blocks, self.support._source, band)
            if info != 0:
                raise NotPositiveDefinite(f"selected inversion failed (LAPACK info {info})")
        return band.reshape(len(st.offsets), st.size)


def factor_madds(counts: np.ndarray) -> float:
    """Multiply-adds of a Cholesky factorisation whose columns have ``counts`` entries:
    ``c (c + 1) / 2`` for a column of ``c`` (a dense one: ``M^3 / 6``)."""
    counts = np.asarray(counts, float)
    return float(np.sum(counts * (counts + 1) / 2))


def band_density(stencil: Stencil, band: np.ndarray, midpoints: Lattice) -> np.ndarray:
    """``S(g) = sum over hinge pairs (m, m') with midpoint g of band[m, m'] c(h_m - h_m')``
    on the midpoint lattice: pair (m, m + o) meets at index ``2 idx(m) + o``; the half
    offsets count twice (the pair and its mirror), the diagonal once."""
    weights = stencil.factor * np.where(np.arange(len(stencil.factor)) == 0, 1.0, 2.0)
    out = np.zeros(midpoints.shape)
    _midpoint_pairs(np.array(stencil.shape), stencil.offsets, weights, np.asarray(band, float), out, True)
    return out


def band_product(stencil: Stencil, band: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``A x`` for the symmetric matrix of ``band`` (K, M) and ``x`` (M, C)."""
    out = np.zeros((stencil.size, x.shape[1]))
    _band_product(
        np.array(stencil.shape), stencil.offsets, np.asarray(band, float), np.asarray(x, float), out
    )
    return out


@numba.njit(nogil=True, cache=True)
def _band_product(shape, offsets, band, x, out):  # pragma: no cover - compiled
    """``out += A x``: each pair (m, m + o_k) of the lattice adds ``band[k, m]`` both ways
    (once on the diagonal, ``k = 0``)."""
    for k in range(len(offsets)):
        o = offsets[k]
        step = (o[0] * shape[1] + o[1]) * shape[2] + o[2]
        for i in range(max(0, -o[0]), shape[0] - max(0, o[0])):
            for j in range(max(0, -o[1]), shape[1] - max(0, o[1])):
                for l in range(max(0, -o[2]), shape[2] - max(0, o[2])):
                    m = (i * shape[1] + j) * shape[2] + l
                    a = band[k, m]
                    for c in range(x.shape[1]):
                        out[m, c] += a * x[m + step, c]
                        if k > 0:
                            out[m + step, c] += a * x[m, c]


def midpoint_band(stencil: Stencil, values: np.ndarray) -> np.ndarray:
    """The band (K, M) with ``band[k, m] = c(o_k) values[2 idx(m) + o_k]``: a function on
    the midpoint lattice read at every stencil pair's midpoint (zero where ``m + o_k``
    leaves the lattice)."""
    out = np.zeros((len(stencil.offsets), stencil.size))
    _midpoint_pairs(
        np.array(stencil.shape), stencil.offsets, stencil.factor, out, np.asarray(values, float), False
    )
    return out


@numba.njit(nogil=True, cache=True)
def _midpoint_pairs(shape, offsets, weights, band, midpoints, to_midpoints):  # pragma: no cover - compiled
    """Over the pairs (m, m + o_k) on the lattice, which meet at ``2 idx(m) + o_k`` of the
    midpoint lattice: ``midpoints[2 idx(m) + o_k] += weights[k] band[k, m]`` if
    ``to_midpoints``, else ``band[k, m] = weights[k] midpoints[2 idx(m) + o_k]``."""
    for k in range(len(offsets)):
        o = offsets[k]
        for i in range(max(0, -o[0]), shape[0] - max(0, o[0])):
            for j in range(max(0, -o[1]), shape[1] - max(0, o[1])):
                for l in range(max(0, -o[2]), shape[2] - max(0, o[2])):
                    m = (i * shape[1] + j) * shape[2] + l
                    g = (2 * i + o[0], 2 * j + o[1], 2 * l + o[2])
                    if to_midpoints:
                        midpoints[g] += weights[k] * band[k, m]
                    else:
                        band[k, m] = weights[k] * midpoints[g]


def dissection(shape, reach) -> np.ndarray:
    """The lattice's hinges (flat indices) in a geometric nested-dissection order: a box is
    cut across its longest axis (in kernel reaches) by a slab ``reach`` hinges wide, which
    no stencil pair crosses; its two halves come first (recursively, until a box is too
    small to cut), the slab last. On these lattices the factor has 6-12 % less work than
    in METIS's order, found in a fraction of METIS's time (bench/RESULTS.md)."""
    index = np.arange(int(np.prod(shape))).reshape(shape)
    reach = np.maximum(np.asarray(reach), 1)
    parts = []

    def cut(lo, hi):
        extent = np.array(hi) - np.array(lo)
        room = np.where(extent > 2 * reach + 1, extent / reach, 0.0)
        d = int(np.argmax(room))
        if room[d] == 0:
            parts.append(index[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]].ravel())
            return
        c = lo[d] + (extent[d] - reach[d]) // 2
        left_hi, right_lo, slab_lo, slab_hi = list(hi), list(lo), list(lo), list(hi)
        left_hi[d], right_lo[d], slab_lo[d], slab_hi[d] = c, c + reach[d], c, c + reach[d]
        cut(lo, left_hi)
        cut(right_lo, hi)
        parts.append(index[slab_lo[0] : slab_hi[0], slab_lo[1] : slab_hi[1], slab_lo[2] : slab_hi[2]].ravel())

    cut([0, 0, 0], list(shape))
    return np.concatenate(parts)


@numba.njit(nogil=True, cache=True)
def _lower_pattern(shape, offsets, rank):  # pragma: no cover - compiled
    """CSC ``indptr``, ``rows`` (sorted) of the stencil's lower triangle with hinge ``m`` at
    row and column ``rank[m]`` (hinges ranked -1 left out), and per entry its band index:
    the pair (m, m + o_k) on the lattice is valued ``band[k, m]``. Gathered by rows, then
    turned into columns, which takes the rows in order."""
    M = shape[0] * shape[1] * shape[2]
    n = 0
    for m in range(M):
        n += rank[m] >= 0
    K = len(offsets)
    flat = (offsets[:, 0] * shape[1] + offsets[:, 1]) * shape[2] + offsets[:, 2]
    rowptr = np.zeros(n + 1, np.int64)
    for step in range(2):  # count the entries per row, then place them
        if step == 1:
            rowptr = np.cumsum(rowptr)
            fill = rowptr[:n].copy()
            cols = np.empty(rowptr[n], np.int64)
            band_index = np.empty(rowptr[n], np.int64)
        for i in range(shape[0]):
            for j in range(shape[1]):
                for l in range(shape[2]):
                    m = (i * shape[1] + j) * shape[2] + l
                    if rank[m] < 0:
                        continue
                    for k in range(K):
                        a, b, c = i + offsets[k, 0], j + offsets[k, 1], l + offsets[k, 2]
                        if 0 <= a < shape[0] and 0 <= b < shape[1] and 0 <= c < shape[2]:
                            p, q = rank[m], rank[m + flat[k]]
                            if q < 0:
                                continue
                            row, col = max(p, q), min(p, q)
                            if step == 0:
                                rowptr[row + 1] += 1
                            else:
                                cols[fill[row]] = col
                                band_index[fill[row]] = k * M + m
                                fill[row] += 1
    indptr = np.zeros(n + 1, np.int64)
    for e in range(len(cols)):
        indptr[cols[e] + 1] += 1
    indptr = np.cumsum(indptr)
    fill = indptr[:n].copy()
    rows, source = np.empty(len(cols), np.int32), np.empty(len(cols), np.int32)
    for row in range(n):
        for e in range(rowptr[row], rowptr[row + 1]):
            col = cols[e]
            rows[fill[col]] = row
            source[fill[col]] = band_index[e]
            fill[col] += 1
    return indptr, rows, source


@numba.njit(nogil=True, cache=True)
def _block_positions(indptr, rows, columns, starts, rowptr, srows, offsets):  # pragma: no cover
    """Index into the blocks of every entry of a lower pattern (CSC; its column ``j`` is
    the factor's column ``c`` where ``columns[c] == j``): by supernodes, each one's rows'
    places in its block looked up in one array."""
    n = len(columns)
    new = np.empty(n, np.int64)
    new[columns] = np.arange(n)
    place = np.full(n, -1, np.int64)
    out = np.empty(indptr[n], np.int32)
    for s in range(len(starts) - 1):
        first, height = rowptr[s], rowptr[s + 1] - rowptr[s]
        for t in range(height):
            place[srows[first + t]] = t
        for c in range(starts[s], starts[s + 1]):
            j = columns[c]
            for p in range(indptr[j], indptr[j + 1]):
                r = new[rows[p]]
                if r < c or place[r] < 0:
                    raise ValueError("an entry of the pattern is missing from the factor's")
                out[p] = offsets[s] + (c - starts[s]) * height + place[r]
        for t in range(height):
            place[srows[first + t]] = -1
    return out


#: Relaxed supernodes (CHOLMOD's defaults): a supernode joins its parent while the two
#: have at most ``NRELAX[0]`` columns, or at most ``NRELAX[1]`` / ``NRELAX[2]`` / any number
#: with explicit zeros below ``ZRELAX[0]`` / ``ZRELAX[1]`` / ``ZRELAX[2]`` of their entries:
#: a few zeros buy larger blocks for BLAS.
NRELAX = (4, 16, 48)
ZRELAX = (0.8, 0.1, 0.05)


@numba.njit(nogil=True, cache=True)
def _symbolic(indptr, rows):  # pragma: no cover - compiled
    """The supernodal structure of the Cholesky factor of a lower pattern (CSC, sorted,
    diagonal included): the columns in the etree's postorder (``columns[new] = old``),
    the relaxed supernodes' first columns ``starts`` (then the column count), and their
    rows (:class:`_Layout`).

    The elimination tree by Liu's algorithm; column counts by the row subtrees (each row
    ``i`` of L is the part of the etree between A's entries of row ``i`` and ``i``);
    fundamental supernodes (a column whose only child is the previous one, with one entry
    fewer), joined by :data:`NRELAX` / :data:`ZRELAX`; each one's rows are its columns,
    A's entries below them and its children's rows below them."""
    n = len(indptr) - 1
    # A's strict lower triangle by rows: row i's columns k < i
    rowstart = np.zeros(n + 1, np.int64)
    for j in range(n):
        for p in range(indptr[j], indptr[j + 1]):
            if rows[p] > j:
                rowstart[rows[p] + 1] += 1
    rowstart = np.cumsum(rowstart)
    rowcols, fill = np.empty(rowstart[n], np.int64), rowstart[:n].copy()
    for j in range(n):
        for p in range(indptr[j], indptr[j + 1]):
            if rows[p] > j:
                rowcols[fill[rows[p]]] = j
                fill[rows[p]] += 1
    # the elimination tree, with path compression
    parent, ancestor = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    for i in range(n):
        for p in range(rowstart[i], rowstart[i + 1]):
            k = rowcols[p]
            while k != -1 and k < i:
                after = ancestor[k]
                ancestor[k] = i
                if after == -1:
                    parent[k] = i
                k = after
    # its postorder (children in increasing order): descendants before ancestors, so A's
    # lower triangle stays lower
    head, sibling = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    for j in range(n - 1, -1, -1):
        if parent[j] != -1:
            sibling[j] = head[parent[j]]
            head[parent[j]] = j
    columns, stack, k = np.empty(n, np.int64), np.empty(n, np.int64), 0
    for root in range(n):
        if parent[root] != -1:
            continue
        top, stack[0] = 0, root
        while top >= 0:
            j = stack[top]
            child = head[j]
            if child == -1:
                top -= 1
                columns[k] = j
                k += 1
            else:
                head[j] = sibling[child]
                top += 1
                stack[top] = child
    new = np.empty(n, np.int64)
    new[columns] = np.arange(n)
    up, children = np.full(n, -1, np.int64), np.zeros(n, np.int64)
    for j in range(n):
        if parent[columns[j]] != -1:
            up[j] = new[parent[columns[j]]]
            children[up[j]] += 1
    # column counts, by the row subtrees
    count, mark = np.ones(n, np.int64), np.full(n, -1, np.int64)
    for i in range(n):
        mark[i] = i
        for p in range(rowstart[columns[i]], rowstart[columns[i] + 1]):
            j = new[rowcols[p]]
            while mark[j] != i:
                count[j] += 1
                mark[j] = i
                j = up[j]
    # fundamental supernodes, then relaxed: supernode s joins s + 1 (and the ones s + 1
    # joined) where s + 1 is its parent
    first = [0]
    for j in range(1, n):
        if not (up[j - 1] == j and count[j - 1] == count[j] + 1 and children[j] == 1):
            first.append(j)
    first.append(n)
    nf = len(first) - 1
    width, height, zeros = np.empty(nf, np.int64), np.empty(nf, np.int64), np.zeros(nf)
    joins = np.zeros(nf, np.bool_)
    for s in range(nf):
        width[s], height[s] = first[s + 1] - first[s], count[first[s]]
    for s in range(nf - 2, -1, -1):
        if up[first[s + 1] - 1] != first[s + 1]:
            continue
        w0, w1 = width[s], width[s + 1]  # s + 1: the supernode it would join, as joined so far
        w = w0 + w1
        added = w0 * (height[s + 1] + w0 - height[s])
        total = zeros[s + 1] + added
        z = total / (w * (w + 1) / 2 + w * (height[s + 1] - w1))
        if (
            w <= NRELAX[0]
            or added == 0
            or (w <= NRELAX[1] and z < ZRELAX[0])
            or (w <= NRELAX[2] and z < ZRELAX[1])
            or z < ZRELAX[2]
        ):
            joins[s] = True
            width[s], height[s], zeros[s] = w, height[s + 1] + w0, total
    bounds = [0]
    s = 0
    while s < nf:  # a supernode: s and those it joined
        while joins[s]:
            s += 1
        s += 1
        bounds.append(first[s])
    starts = np.array(bounds)
    # each supernode's rows: its columns, A's entries below them, its children's below them
    ns = len(starts) - 1
    node = np.empty(n, np.int64)
    for t in range(ns):
        node[starts[t] : starts[t + 1]] = t
    kids, next_kid = np.full(ns, -1, np.int64), np.full(ns, -1, np.int64)
    mark[:] = -1
    heights, gathered, pieces = np.empty(ns, np.int64), np.empty(n, np.int64), []
    for t in range(ns):
        f, e = starts[t], starts[t + 1]
        m = 0
        for c in range(f, e):
            mark[c] = t
            gathered[m] = c
            m += 1
        for c in range(f, e):
            for p in range(indptr[columns[c]], indptr[columns[c] + 1]):
                i = new[rows[p]]
                if i >= e and mark[i] != t:
                    mark[i] = t
                    gathered[m] = i
                    m += 1
        kid = kids[t]
        while kid != -1:
            for i in pieces[kid]:
                if i >= e and mark[i] != t:
                    mark[i] = t
                    gathered[m] = i
                    m += 1
            kid = next_kid[kid]
        pieces.append(np.sort(gathered[:m]))
        heights[t] = m
        if up[e - 1] != -1:
            q = node[up[e - 1]]
            next_kid[t] = kids[q]
            kids[q] = t
    rowptr = np.zeros(ns + 1, np.int64)
    rowptr[1:] = np.cumsum(heights)
    supernode_rows = np.empty(rowptr[ns], np.int64)
    for t in range(ns):
        supernode_rows[rowptr[t] : rowptr[t + 1]] = pieces[t]
    return columns, starts, rowptr, supernode_rows


@numba.njit(nogil=True, cache=True)
def _extent(rowptr, starts):  # pragma: no cover - compiled
    """The widest supernode's columns and the tallest one's rows (the kernels' buffers)."""
    widest, tallest = 1, 1
    for s in range(len(starts) - 1):
        widest = max(widest, starts[s + 1] - starts[s])
        tallest = max(tallest, rowptr[s + 1] - rowptr[s])
    return widest, tallest


@numba.njit(nogil=True, cache=True)
def _holder(rowptr, rows, starts, offsets, column_node, R, b, pos, rel):  # pragma: no cover
    """The run ``R[b:b1]`` of a supernode's rows R whose columns one later supernode holds
    (R is a clique of the filled graph, so all of ``R[a]``, a >= b, are among its rows):
    ``b1``, and column ``R[bb]``'s place ``origin + R[bb] * height`` in its block, with
    ``rel[a]`` the row of ``R[a]`` there. ``pos`` is scratch (one entry per column)."""
    s2 = column_node[R[b]]
    first = rowptr[s2]
    height = rowptr[s2 + 1] - first
    for t in range(height):
        pos[rows[first + t]] = t
    for a in range(b, len(R)):
        rel[a] = pos[R[a]]
    b1 = b
    while b1 < len(R) and R[b1] < starts[s2 + 1]:
        b1 += 1
    return b1, offsets[s2] - starts[s2] * height, height


@numba.njit(nogil=True, cache=True)
def _factor_of(layout, band, source, shift, blocks):  # pragma: no cover - compiled
    """:func:`_factor` of the band's matrix (``band`` flat) ``+ shift I``, placed in
    ``blocks`` (zeros) first: the whole factorisation without the GIL."""
    for t in range(len(source)):
        blocks[layout.position[t]] = band[source[t]]
    for d in layout.diagonal:
        blocks[d] += shift
    return _factor(layout.rowptr, layout.rows, layout.starts, layout.offsets, layout.column_node, blocks)


@numba.njit(nogil=True, cache=True)
def _inverse_band(layout, blocks, source, band):  # pragma: no cover - compiled
    """:func:`_selected_inverse` in place of a factor's ``blocks``, put in ``band`` (flat) at
    the stencil's pairs; LAPACK's info."""
    info = _selected_inverse(
        layout.rowptr, layout.rows, layout.starts, layout.offsets, layout.column_node, blocks
    )
    for t in range(len(source)):
        band[source[t]] = blocks[layout.position[t]]
    return info


@numba.njit(nogil=True, cache=True)
def _factor(rowptr, rows, starts, offsets, column_node, blocks):  # pragma: no cover - compiled
    """Supernodal Cholesky in place: ``blocks`` hold the lower triangle of the matrix in the
    layout of :class:`_Layout` and end holding L. Right-looking, by supernodes from the
    first: for columns J with rows R below them, ``L_JJ`` by LAPACK, ``L_RJ = A_RJ L_JJ^-T``,
    and ``L_RJ L_RJ^T`` subtracted from the supernodes holding R's columns (R is a clique
    of the filled graph, so each of its entries is stored there), a panel of one supernode's
    columns at a time. Returns 0, or 1 + the supernode whose diagonal block is not
    positive definite."""
    pos = np.empty(len(column_node), np.int64)
    widest, tallest = _extent(rowptr, starts)
    update, rel = np.empty(tallest * widest), np.empty(tallest, np.int64)
    for s in range(len(starts) - 1):
        w = starts[s + 1] - starts[s]
        nr = rowptr[s + 1] - rowptr[s]
        r = nr - w
        blk = blocks[offsets[s] : offsets[s + 1]]
        if _lapack.potrf(blk, w, nr) != 0:
            return s + 1
        if r == 0:
            continue
        below = blk[w:]
        _lapack.trsm(_lapack.R, _lapack.T, r, w, 1.0, blk, nr, below, nr)
        R = rows[rowptr[s] + w : rowptr[s + 1]]
        b = 0
        while b < r:  # the columns of R in one supernode: rows b.. of their panel
            b1, origin, nr2 = _holder(rowptr, rows, starts, offsets, column_node, R, b, pos, rel)
            h, g, panel = r - b, b1 - b, below[b:]  # the panel's square top by syrk, the rest by gemm
            _lapack.syrk(g, w, 1.0, panel, nr, 0.0, update, h)
            if h > g:
                _lapack.gemm(
                    _lapack.N, _lapack.T, h - g, g, w, 1.0, panel[g:], nr, panel, nr, 0.0, update[g:], h
                )
            for bb in range(b, b1):
                column = blocks[origin + R[bb] * nr2 :]
                base = (bb - b) * h - b
                for a in range(bb, r):
                    column[rel[a]] -= update[base + a]
            b = b1
    return 0


@numba.njit(nogil=True, cache=True)
def _solve(rowptr, rows, starts, offsets, blocks, y):  # pragma: no cover - compiled
    """``y <- (L L^T)^-1 y`` in place for ``y`` (n, k) C-ordered (so each supernode's rows
    are a column-major (k, w) block): forward by supernodes, then back."""
    k = y.shape[1]
    flat = y.ravel()
    z = np.empty(_extent(rowptr, starts)[1] * k)
    for backward in range(2):
        for step in range(len(starts) - 1):
            s = len(starts) - 2 - step if backward else step
            f, w = starts[s], starts[s + 1] - starts[s]
            nr = rowptr[s + 1] - rowptr[s]
            r = nr - w
            blk = blocks[offsets[s] : offsets[s + 1]]
            yJ = flat[f * k : (f + w) * k]
            R = rows[rowptr[s] + w : rowptr[s + 1]]
            if backward:  # x_J^T = (y_J^T - x_R^T L_RJ) L_JJ^-1
                if r > 0:
                    for a in range(r):
                        z[a * k : (a + 1) * k] = y[R[a]]
                    _lapack.gemm(_lapack.N, _lapack.N, k, w, r, -1.0, z, k, blk[w:], nr, 1.0, yJ, k)
                _lapack.trsm(_lapack.R, _lapack.N, k, w, 1.0, blk, nr, yJ, k)
            else:  # x_J^T = y_J^T L_JJ^-T, then y_R^T -= x_J^T L_RJ^T
                _lapack.trsm(_lapack.R, _lapack.T, k, w, 1.0, blk, nr, yJ, k)
                if r > 0:
                    _lapack.gemm(_lapack.N, _lapack.T, k, r, w, 1.0, yJ, k, blk[w:], nr, 0.0, z, k)
                    for a in range(r):
                        y[R[a]] -= z[a * k : (a + 1) * k]


@numba.njit(nogil=True, cache=True)
def _selected_inverse(rowptr, rows, starts, offsets, column_node, blocks):  # pragma: no cover
    """``(L L^T)^-1`` on the factor's pattern, in place of L in ``blocks`` (lower triangles).

    Takahashi, by supernodes from the last: for columns J with rows R below them,
    ``Y = L_RJ L_JJ^-1``, ``S_RJ = -S_RR Y`` and ``S_JJ = (L_JJ L_JJ^T)^-1 - Y^T S_RJ``;
    ``S_RR`` is gathered from later supernodes (R is a clique of the filled graph, so each
    of its entries is stored there). Returns LAPACK's info of the first failure, or 0.
    """
    pos = np.empty(len(column_node), np.int64)
    widest, tallest = _extent(rowptr, starts)
    srr, rel = np.empty(tallest * tallest), np.empty(tallest, np.int64)
    Y = np.empty(tallest * widest)
    for s in range(len(starts) - 2, -1, -1):
        w = starts[s + 1] - starts[s]
        nr = rowptr[s + 1] - rowptr[s]
        r = nr - w
        blk = blocks[offsets[s] : offsets[s + 1]]
        if r > 0:
            for c in range(w):  # Y = L_RJ L_JJ^-1, column-major (r, w)
                Y[c * r : (c + 1) * r] = blk[c * nr + w : (c + 1) * nr]
            _lapack.trsm(_lapack.R, _lapack.N, r, w, 1.0, blk, nr, Y, r)
        info = _lapack.potri(blk, w, nr)
        if info != 0:
            return info
        if r == 0:
            continue
        R = rows[rowptr[s] + w : rowptr[s + 1]]
        b = 0
        while b < r:  # S_RR's lower triangle, column-major (r, r), from R's supernodes
            b1, origin, nr2 = _holder(rowptr, rows, starts, offsets, column_node, R, b, pos, rel)
            for bb in range(b, b1):
                column = blocks[origin + R[bb] * nr2 :]
                for a in range(bb, r):
                    srr[bb * r + a] = column[rel[a]]
            b = b1
        below = blk[w:]
        _lapack.symm(r, w, -1.0, srr, r, Y, r, 0.0, below, nr)  # S_RJ
        _lapack.gemm(_lapack.T, _lapack.N, w, w, r, -1.0, Y, r, below, nr, 1.0, blk, nr)  # S_JJ
    return 0
