"""The precision's stencil and the matrices on it: bands, supports and factors.

Two hinges couple through ``c(h_m - h_m') = exp(-sum_d gamma_d (h_md - h_m'd)^2 / 2)``
(:mod:`bdf.statistics`), so pairs whose coupling is below the kernel's cutoff are dropped: the
precision is a 3-D *stencil* (the offsets ``o`` with ``c(o) >= cutoff``) around every
hinge. Matrices on that pattern are kept as *bands*: ``band[k, m] = A[m, m + o_k]`` for
the half of the offsets that is lexicographically >= 0 (the other half by symmetry),
zeros where ``m + o_k`` leaves the lattice.

A band is factored in a geometric nested dissection of the lattice (:func:`dissection`),
on the hinges it touches (:class:`Support`): a hinge whose Gram diagonal is zero has a
zero row (``G`` is positive semi-definite), so ``G + shift I`` is ``shift`` there, apart
from the rest. Sparse traffic on a large lattice, and each heading sector of a
directional map, touch a fraction of the hinges: the factor's work falls roughly with its
cube. Where a class touches most of the hinges its total touches, it is factored on the
total's support instead (:data:`COVER`): one analysis serves them all. The support's
pattern is analysed once (:mod:`bdf.sparse.symbolic`) and factored per shift
(:mod:`bdf.sparse.supernodal`); the :class:`Factor` gives the log-determinant (evidence),
solves (posterior mean) and the inverse on the stencil (variance density).
"""

from __future__ import annotations

import functools
import threading

import numba
import numpy as np
import scipy.sparse as sp

from bdf.grid import Lattice
from bdf.kernel import Kernel
from bdf.sparse import supernodal
from bdf.sparse.symbolic import analyse

#: A band is factored on a kept support with up to this many times its own hinges
#: (:meth:`Stencil.support`): exact either way (the extra hinges are decoupled).
COVER = 1.25


class NotPositiveDefinite(ValueError):
    """The precision lost positive definiteness (a bad fixed alpha or beta)."""


@functools.lru_cache(maxsize=16)
def lattice_stencil(shape: tuple[int, int, int], step: tuple, kernel: Kernel) -> Stencil:
    """The pattern of a lattice's precision: cached per lattice and kernel."""
    return Stencil(shape, np.array(step), kernel)


def stencil_on(grid: Lattice, kernel: Kernel) -> Stencil:
    """The precision's stencil on a hinge lattice (cached)."""
    return lattice_stencil(tuple(grid.shape), tuple(np.asarray(grid.step, float).tolist()), kernel)


class Stencil:
    """Offsets ``o`` (hinge steps) with ``c(o) >= cutoff``: the half kept in bands
    (``offsets``, lexicographically >= 0, zero first), their couplings ``kernel``
    (:meth:`bdf.kernel.Kernel.couplings`), and a nested-dissection order of the lattice
    (:func:`dissection`)."""

    #: Supports kept per stencil: a directional map's classes use the total's, or their own
    #: where they touch fewer hinges (:data:`COVER`); refits find them all here.
    SUPPORTS = 4

    def __init__(self, shape, step, kernel: Kernel):
        self._key = (tuple(shape), tuple(step.tolist()), kernel)
        self.shape, self.cutoff = tuple(shape), kernel.cutoff
        self.offsets, self.kernel, self.reach = kernel.couplings(step, shape)
        self._lock = threading.RLock()  # the lazy parts build on one another
        self._order = None
        self._supports: dict[bytes, Support] = {}

    def __reduce__(self):
        """Pickled as its key: unpickled, it is the cached stencil of that process (posteriors
        computed in another process arrive without their factors, see RegionMaps)."""
        return lattice_stencil, self._key

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
    layout of the factor's blocks (:class:`~bdf.sparse.symbolic.Layout`), analysed at the
    first factorisation.
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
        on the rest): the matrix placed in the blocks, factored in place
        (:func:`~bdf.sparse.supernodal.factorise`)."""
        if not len(self.order):
            return Factor(self, None, shift)
        with self._lock:
            if self.layout is None:
                self.layout = analyse(self._indptr, self._rows)
        lay = self.layout
        blocks = np.zeros(lay.offsets[-1])  # fresh pages come zeroed
        failed = supernodal.factor_band(
            lay, np.ascontiguousarray(band, float).ravel(), self._source, shift, blocks
        )
        if failed:
            raise NotPositiveDefinite(f"the factorisation broke down at supernode {failed - 1}")
        return Factor(self, blocks, shift)


class Factor:
    """One factorisation ``P (A + shift I) P^T = L L^T`` of a support's matrix ``A`` (in its
    order; ``P`` only postorders it), as the blocks of its supernodes (:class:`~bdf.sparse.symbolic.Layout`);
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
            supernodal.solve(lay.rowptr, lay.rows, lay.starts, lay.offsets, self._blocks, y)
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
            info = supernodal.inverse_band(self.support.layout, blocks, self.support._source, band)
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
    weights = stencil.kernel * np.where(np.arange(len(stencil.kernel)) == 0, 1.0, 2.0)
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
        np.array(stencil.shape), stencil.offsets, stencil.kernel, out, np.asarray(values, float), False
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
    small to cut), the slab last: each slab is a separator (no pair couples its halves).
    On these lattices it leaves less fill than METIS, in a fraction of its time."""
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
