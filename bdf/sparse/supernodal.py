"""Supernodal Cholesky factorisation, solves and selected inversion, compiled.

Each kernel works on the layout :func:`bdf.sparse.symbolic.analyse` gives: the factor as
the dense blocks of its supernodes, one after another in one flat array (a supernode's
rows by its columns, column-major). Each is one compiled call with LAPACK and BLAS
(:mod:`bdf.sparse._lapack`) that releases the GIL, so that the classes of a directional
map are factored side by side in threads.

- :func:`factorise`: right-looking, by supernodes from the first.
- :func:`solve`: forward and back substitution by supernodes, many right-hand sides at once.
- :func:`selected_inverse`: the inverse on the factor's pattern by the Takahashi
  recursions, by supernodes from the last (Takahashi, Fagan and Chin, 1973; the
  supernodal form of Lin et al.'s SelInv): all the variance density needs.

In each, a supernode's rows below its columns form a clique of the filled graph, so every
entry they touch is stored in a later supernode (:func:`_holder` finds it).
"""

from __future__ import annotations

import numba
import numpy as np

from bdf.sparse import _lapack


@numba.njit(nogil=True, cache=True)
def _extent(rowptr, starts):  # pragma: no cover - compiled
    """The widest supernode's columns and the tallest one's rows (the kernels' buffers)."""
    widest, tallest = 1, 1
    for s in range(len(starts) - 1):
        widest = max(widest, starts[s + 1] - starts[s])
        tallest = max(tallest, rowptr[s + 1] - rowptr[s])
    return widest, tallest


@numba.njit(nogil=True, cache=True)
def _holder(rowptr, rows, starts, offsets, column_node, R, b, pos, place):  # pragma: no cover
    """The run ``R[b:run_end]`` of a supernode's rows R whose columns one later supernode holds
    (R is a clique of the filled graph, so all of ``R[a]``, a >= b, are among its rows):
    ``run_end``, and column ``R[col]``'s place ``origin + R[col] * height`` in its block, with
    ``place[a]`` the row of ``R[a]`` there. ``pos`` is scratch (one entry per column)."""
    s2 = column_node[R[b]]
    first = rowptr[s2]
    height = rowptr[s2 + 1] - first
    for t in range(height):
        pos[rows[first + t]] = t
    for a in range(b, len(R)):
        place[a] = pos[R[a]]
    run_end = b
    while run_end < len(R) and R[run_end] < starts[s2 + 1]:
        run_end += 1
    return run_end, offsets[s2] - starts[s2] * height, height


@numba.njit(nogil=True, cache=True)
def factor_band(layout, band, source, shift, blocks):  # pragma: no cover - compiled
    """:func:`factorise` of the band's matrix (``band`` flat) ``+ shift I``, placed in
    ``blocks`` (zeros) first: the whole factorisation without the GIL."""
    for t in range(len(source)):
        blocks[layout.position[t]] = band[source[t]]
    for d in layout.diagonal:
        blocks[d] += shift
    return factorise(layout.rowptr, layout.rows, layout.starts, layout.offsets, layout.column_node, blocks)


@numba.njit(nogil=True, cache=True)
def inverse_band(layout, blocks, source, band):  # pragma: no cover - compiled
    """:func:`selected_inverse` in place of a factor's ``blocks``, put in ``band`` (flat) at
    the stencil's pairs; LAPACK's info."""
    info = selected_inverse(
        layout.rowptr, layout.rows, layout.starts, layout.offsets, layout.column_node, blocks
    )
    for t in range(len(source)):
        band[source[t]] = blocks[layout.position[t]]
    return info


@numba.njit(nogil=True, cache=True)
def factorise(rowptr, rows, starts, offsets, column_node, blocks):  # pragma: no cover - compiled
    """Supernodal Cholesky in place: ``blocks`` hold the lower triangle of the matrix in the
    layout of :class:`~bdf.sparse.symbolic.Layout` and end holding L. Right-looking, by supernodes from the
    first: for columns J with rows R below them, ``L_JJ`` by LAPACK, ``L_RJ = A_RJ L_JJ^-T``,
    and ``L_RJ L_RJ^T`` subtracted from the supernodes holding R's columns (R is a clique
    of the filled graph, so each of its entries is stored there), a panel of one supernode's
    columns at a time. Returns 0, or 1 + the supernode whose diagonal block is not
    positive definite."""
    pos = np.empty(len(column_node), np.int64)
    widest, tallest = _extent(rowptr, starts)
    update, place = np.empty(tallest * widest), np.empty(tallest, np.int64)
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
            run_end, origin, holder_rows = _holder(
                rowptr, rows, starts, offsets, column_node, R, b, pos, place
            )
            h, g, panel = r - b, run_end - b, below[b:]  # the panel's square top by syrk, the rest by gemm
            _lapack.syrk(g, w, 1.0, panel, nr, 0.0, update, h)
            if h > g:
                _lapack.gemm(
                    _lapack.N, _lapack.T, h - g, g, w, 1.0, panel[g:], nr, panel, nr, 0.0, update[g:], h
                )
            for col in range(b, run_end):
                column = blocks[origin + R[col] * holder_rows :]
                base = (col - b) * h - b
                for a in range(col, r):
                    column[place[a]] -= update[base + a]
            b = run_end
    return 0


@numba.njit(nogil=True, cache=True)
def solve(rowptr, rows, starts, offsets, blocks, y):  # pragma: no cover - compiled
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
def selected_inverse(rowptr, rows, starts, offsets, column_node, blocks):  # pragma: no cover
    """``(L L^T)^-1`` on the factor's pattern, in place of L in ``blocks`` (lower triangles).

    Takahashi, by supernodes from the last: for columns J with rows R below them,
    ``Y = L_RJ L_JJ^-1``, ``S_RJ = -S_RR Y`` and ``S_JJ = (L_JJ L_JJ^T)^-1 - Y^T S_RJ``;
    ``S_RR`` is gathered from later supernodes (R is a clique of the filled graph, so each
    of its entries is stored there). Returns LAPACK's info of the first failure, or 0.
    """
    pos = np.empty(len(column_node), np.int64)
    widest, tallest = _extent(rowptr, starts)
    srr, place = np.empty(tallest * tallest), np.empty(tallest, np.int64)
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
            run_end, origin, holder_rows = _holder(
                rowptr, rows, starts, offsets, column_node, R, b, pos, place
            )
            for col in range(b, run_end):
                column = blocks[origin + R[col] * holder_rows :]
                for a in range(col, r):
                    srr[col * r + a] = column[place[a]]
            b = run_end
        below = blk[w:]
        _lapack.symm(r, w, -1.0, srr, r, Y, r, 0.0, below, nr)  # S_RJ
        _lapack.gemm(_lapack.T, _lapack.N, w, w, r, -1.0, Y, r, below, nr, 1.0, blk, nr)  # S_JJ
    return 0
