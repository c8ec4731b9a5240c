"""The precision's sparse algebra: stencil, CHOLMOD factorisation, selected inversion.

Two hinges couple through ``c(h_m - h_m') = exp(-sum_d gamma_d (h_md - h_m'd)^2 / 2)``
(:mod:`bdf.stats`), so pairs whose factor is below the kernel ``cutoff`` are dropped:
the precision is a 3-D *stencil* (the offsets ``o`` with ``c(o) >= cutoff``) around every
hinge. Matrices on that pattern are kept as *bands*: ``band[k, m] = A[m, m + o_k]`` for
the half of the offsets that is lexicographically >= 0 (the other half by symmetry),
zeros where ``m + o_k`` leaves the lattice.

A band is factored by CHOLMOD (scikit-sparse; fill-reducing ordering, supernodal, BLAS)
after one symbolic analysis per pattern; the factor gives the log-determinant (evidence)
and the solves (posterior mean). The variance density needs the posterior covariance
only on the stencil's pairs, which lie in the factor's pattern: :func:`selected_inverse`
computes the inverse on that pattern by the Takahashi recursions, supernode by supernode
(dense blocks with BLAS), compiled with numba.
"""

from __future__ import annotations

import functools
import threading

import numba
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze

from bdf.grid import Lattice


class NotPositiveDefinite(ValueError):
    """The precision lost positive definiteness (a bad fixed alpha or beta)."""


@functools.lru_cache(maxsize=16)
def stencil(shape: tuple[int, int, int], step: tuple, gamma: tuple, cutoff: float) -> Stencil:
    """The pattern of a lattice's precision: cached per lattice and kernel."""
    return Stencil(shape, np.array(step), np.array(gamma), cutoff)


class Stencil:
    """Offsets ``o`` (hinge steps) with ``c(o) >= cutoff``: the half kept in bands
    (``offsets``, lexicographically >= 0, zero first) and the CSC pattern they give."""

    def __init__(self, shape, step, gamma, cutoff):
        self.shape = tuple(shape)
        steps = gamma * step**2 / 2.0  # exponent per squared hinge step, per axis
        limit = np.log(1.0 / cutoff)
        reach = np.minimum(np.floor(np.sqrt(limit / steps)).astype(int), np.array(shape) - 1)
        axes = [np.arange(-r, r + 1) for r in reach]
        o = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        o = o[(o**2 @ steps) <= limit]
        half = (o[:, 0] > 0) | ((o[:, 0] == 0) & ((o[:, 1] > 0) | ((o[:, 1] == 0) & (o[:, 2] >= 0))))
        o = o[half]
        self.offsets = o[np.lexsort((o[:, 2], o[:, 1], o[:, 0]))]
        self.factor = np.exp(-(self.offsets**2 @ steps))  # c(o)
        self._lock = threading.Lock()
        self._pattern = None
        self._symbolic = None
        self._positions = None

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

    def midpoints(self, k: int) -> tuple[slice, slice, slice]:
        """Slices of the midpoint lattice where the pairs of :meth:`valid` meet (``2 m + o_k``)."""
        o = self.offsets[k]
        return tuple(
            slice(2 * s.start + o[d], 2 * (s.stop - 1) + o[d] + 1, 2) for d, s in enumerate(self.valid(k))
        )

    def pattern(self):
        """``(csc_template, source)``: a symmetric CSC matrix of the pattern and, per stored
        entry, its index into a flattened band (``k * M + m``)."""
        with self._lock:
            if self._pattern is None:
                M = self.size
                rows, cols, src = [], [], []
                for k in range(len(self.offsets)):
                    m, partner = self.pairs(k)
                    rows += [m, partner] if k else [m]
                    cols += [partner, m] if k else [m]
                    src += [k * M + m] * (2 if k else 1)
                rows, cols, src = np.concatenate(rows), np.concatenate(cols), np.concatenate(src)
                order = np.lexsort((rows, cols))
                rows, cols, src = rows[order], cols[order], src[order]
                indptr = np.searchsorted(cols, np.arange(M + 1))
                template = sp.csc_matrix((np.ones(len(rows)), rows, indptr), shape=(M, M))
                self._pattern = template, src
            return self._pattern

    def matrix(self, band: np.ndarray) -> sp.csc_matrix:
        """The symmetric sparse matrix of ``band`` (len(offsets), M)."""
        template, src = self.pattern()
        out = template.copy()
        out.data = np.asarray(band).ravel()[src]
        return out

    def factor_of(self, band: np.ndarray, shift: float) -> Factor:
        """CHOLMOD's factor of ``matrix(band) + shift I``; the analysis (ordering, pattern of
        the factor) is done once per stencil."""
        A = self.matrix(band)
        with self._lock:
            if self._symbolic is None:
                self._symbolic = analyze(A, mode="supernodal")
            symbolic = self._symbolic
        try:
            numeric = symbolic.cholesky(A, beta=shift)
        except CholmodNotPositiveDefiniteError as exc:
            raise NotPositiveDefinite(str(exc)) from None
        return Factor(self, numeric)


class Factor:
    """One numeric factorisation ``P (A + shift I) P^T = L L^T``."""

    def __init__(self, stencil: Stencil, numeric):
        self.stencil, self._numeric = stencil, numeric
        self._lower = None

    def logdet(self) -> float:
        return float(self._numeric.logdet())

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._numeric.solve_A(b)

    def lower(self) -> sp.csc_matrix:
        """L, column-sorted CSC (CHOLMOD converts its supernodes once)."""
        if self._lower is None:
            self._lower = self._numeric.L().tocsc()
            self._lower.sort_indices()
        return self._lower

    @property
    def nnz(self) -> int:
        """Entries of L (what the factorisation and the selected inversion work on)."""
        return int(self.lower().nnz)

    @property
    def madds(self) -> float:
        """Multiply-adds of the factorisation: sum over columns of (entries in the column)^2."""
        counts = np.diff(self.lower().indptr).astype(float)
        return float(np.sum(counts * counts))

    def inverse_band(self) -> np.ndarray:
        """The inverse on the stencil, as a band (len(offsets), M): selected inversion."""
        L = self.lower()
        starts = _supernodes(L.indptr, L.indices)
        values = _selected_inverse(L.indptr, L.indices, L.data, starts)
        where, source = self._stencil_positions()
        band = np.zeros(len(self.stencil.offsets) * self.stencil.size)
        band[where] = values[source]
        return band.reshape(len(self.stencil.offsets), self.stencil.size)

    def _stencil_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Where each stencil pair sits in L's values (lower triangle, permuted order), as
        (flat band index, index into L.data). Every factor of one analysis has the same
        ordering and pattern, so this is computed once per stencil."""
        st = self.stencil
        with st._lock:
            if st._positions is None:
                L = self.lower()
                inverse_perm = np.empty(st.size, np.int64)
                inverse_perm[self._numeric.P()] = np.arange(st.size)
                where, source = [], []
                for k in range(len(st.offsets)):
                    m, partner = st.pairs(k)
                    a, b = inverse_perm[m], inverse_perm[partner]
                    where.append(k * st.size + m)
                    source.append(_positions(L.indptr, L.indices, np.maximum(a, b), np.minimum(a, b)))
                st._positions = np.concatenate(where), np.concatenate(source)
            return st._positions


def band_density(stencil: Stencil, band: np.ndarray, midpoints: Lattice) -> np.ndarray:
    """``S(g) = sum over hinge pairs (m, m') with midpoint g of band[m, m'] c(h_m - h_m')``
    on the midpoint lattice: pair (m, m + o) meets at index ``2 idx(m) + o``; the half
    offsets count twice (the pair and its mirror), the diagonal once."""
    out = np.zeros(midpoints.shape)
    for k in range(len(stencil.offsets)):
        weight = stencil.factor[k] * (1.0 if k == 0 else 2.0)
        out[stencil.midpoints(k)] += weight * band[k].reshape(stencil.shape)[stencil.valid(k)]
    return out


@numba.njit(cache=True)
def _positions(indptr, indices, rows, cols):  # pragma: no cover - compiled
    """Index into ``indices`` of every (row, col) entry (sorted columns; must exist)."""
    out = np.empty(len(rows), np.int64)
    for t in range(len(rows)):
        lo, hi = indptr[cols[t]], indptr[cols[t] + 1]
        while lo < hi:
            mid = (lo + hi) // 2
            if indices[mid] < rows[t]:
                lo = mid + 1
            else:
                hi = mid
        if lo == indptr[cols[t] + 1] or indices[lo] != rows[t]:
            raise ValueError("an entry of the stencil is missing from the factor's pattern")
        out[t] = lo
    return out


@numba.njit(cache=True)
def _supernodes(indptr, indices):  # pragma: no cover - compiled
    """First column of each fundamental supernode (columns j, j+1 share one when column
    j + 1's pattern is column j's without j), and the column count at the end."""
    n = len(indptr) - 1
    starts = [0]
    for j in range(1, n):
        previous = indptr[j] - indptr[j - 1]
        if not (
            indptr[j + 1] - indptr[j] == previous - 1 and previous > 1 and indices[indptr[j - 1] + 1] == j
        ):
            starts.append(j)
    starts.append(n)
    return np.array(starts)


def _selected_inverse(indptr, indices, data, starts) -> np.ndarray:
    """``(L L^T)^-1`` on the pattern of the lower factor ``L`` (CSC, sorted, diagonal first).

    Takahashi, by supernodes from the last: for columns J with rows R below them,
    ``Y = L_RJ L_JJ^-1``, ``S_RJ = -S_RR Y`` and ``S_JJ = (L_JJ L_JJ^T)^-1 - Y^T S_RJ``;
    ``S_RR`` is gathered from later supernodes (R is a clique of the filled graph, so each
    of its entries is stored there). The dense steps are LAPACK/BLAS calls (all cores),
    the gathers compiled loops.
    """
    n = len(indptr) - 1
    ns = len(starts) - 1
    col_sn = np.repeat(np.arange(ns), np.diff(starts))
    firsts = starts[:-1]
    heights = indptr[firsts + 1] - indptr[firsts]
    offs = np.concatenate([[0], np.cumsum(heights * np.diff(starts))])
    blocks = np.empty(offs[-1])
    pos = np.full(n, -1, np.int64)
    for s in range(ns - 1, -1, -1):
        f, l = starts[s], starts[s + 1]
        w, nr = l - f, heights[s]
        r = nr - w
        Lb = _dense_block(indptr, data, f, w, nr)
        blk = blocks[offs[s] : offs[s + 1]].reshape(nr, w)
        LJJ = Lb[:w]
        SJJ, info = sla.lapack.dpotri(LJJ, lower=1, overwrite_c=1)
        if info != 0:
            raise NotPositiveDefinite(f"selected inversion failed (LAPACK info {info})")
        _mirror_lower(SJJ)
        if r > 0:
            Y = sla.solve_triangular(LJJ, Lb[w:].T, lower=True, trans="T", check_finite=False).T
            R = indices[indptr[f] + w : indptr[f + 1]]
            Srr = _gather(indptr, indices, starts, col_sn, offs, blocks, pos, R)
            SRJ = -(Srr @ Y)
            SJJ -= Y.T @ SRJ
            blk[w:] = SRJ
        blk[:w] = SJJ
    return _scatter(indptr, starts, offs, blocks, len(data))


@numba.njit(cache=True)
def _mirror_lower(A):  # pragma: no cover - compiled
    """Copy the lower triangle of the square ``A`` onto its upper one, in place."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            A[i, j] = A[j, i]


@numba.njit(cache=True)
def _dense_block(indptr, data, f, w, nr):  # pragma: no cover - compiled
    """Columns f .. f + w - 1 of L as a dense (nr, w) block (a supernode's trapezoid)."""
    Lb = np.zeros((nr, w))
    for c in range(w):
        p = indptr[f + c]
        for t in range(nr - c):
            Lb[c + t, c] = data[p + t]
    return Lb


@numba.njit(cache=True)
def _gather(indptr, indices, starts, col_sn, offs, blocks, pos, R):  # pragma: no cover - compiled
    """``S[R, R]`` (dense, symmetric) from the blocks of the supernodes holding R's columns."""
    r = len(R)
    Srr = np.empty((r, r))
    b = 0
    while b < r:
        s2 = col_sn[R[b]]
        f2, l2 = starts[s2], starts[s2 + 1]
        rows2 = indices[indptr[f2] : indptr[f2 + 1]]
        for t in range(len(rows2)):
            pos[rows2[t]] = t
        blk2 = blocks[offs[s2] : offs[s2 + 1]].reshape(len(rows2), l2 - f2)
        b1 = b
        while b1 < r and R[b1] < l2:
            b1 += 1
        for bb in range(b, b1):
            cc = R[bb] - f2
            for a in range(bb, r):
                v = blk2[pos[R[a]], cc]
                Srr[a, bb] = v
                Srr[bb, a] = v
        for t in range(len(rows2)):
            pos[rows2[t]] = -1
        b = b1
    return Srr


@numba.njit(cache=True)
def _scatter(indptr, starts, offs, blocks, nnz):  # pragma: no cover - compiled
    """The blocks back on L's pattern (lower triangle, column by column)."""
    out = np.empty(nnz)
    for s in range(len(starts) - 1):
        f, l = starts[s], starts[s + 1]
        w = l - f
        nr = indptr[f + 1] - indptr[f]
        blk = blocks[offs[s] : offs[s + 1]].reshape(nr, w)
        for c in range(w):
            p = indptr[f + c]
            for t in range(nr - c):
                out[p + t] = blk[c + t, c]
    return out
