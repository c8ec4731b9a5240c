"""Symbolic analysis: from a lower pattern to the layout of its Cholesky factor's supernodes.

Split as CSparse splits it (Davis, *Direct Methods for Sparse Linear Systems*, ch. 4), one
function per step: the pattern by rows (:func:`lower_rows`), the elimination tree by Liu's
algorithm (:func:`elimination_tree`), its postorder (:func:`postorder`), the factor's
column counts by row subtrees (:func:`column_counts`), fundamental supernodes
(:func:`fundamental_supernodes`) relaxed as CHOLMOD relaxes them
(:func:`relaxed_supernodes`), and each supernode's rows (:func:`supernode_rows`).
:func:`analyse` runs them and places every entry of the pattern in the supernodes' dense
blocks (:class:`Layout`), which :mod:`bdf.sparse.supernodal` factors and inverts.

Patterns are CSC ``indptr``, ``rows``: the lower triangle, rows sorted, diagonal included.
A postorder keeps descendants before ancestors, so the pattern stays lower in it.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

#: Relaxed supernodes (CHOLMOD's defaults): a supernode joins its parent while the two
#: have at most ``NRELAX[0]`` columns, or at most ``NRELAX[1]`` / ``NRELAX[2]`` / any number
#: with explicit zeros below ``ZRELAX[0]`` / ``ZRELAX[1]`` / ``ZRELAX[2]`` of their entries:
#: a few zeros buy larger blocks for BLAS.
NRELAX = (4, 16, 48)
ZRELAX = (0.8, 0.1, 0.05)


class Layout(NamedTuple):
    """The factor's supernodes: their first columns (then the column count), rows (each
    one's sorted, its own columns first: ``rows[rowptr[s]:rowptr[s + 1]]``) and block
    offsets (its rows by its columns, column-major, one after another); each column's
    supernode and diagonal entry; the pattern's columns in the factor's order
    (``columns[new] = old``); per entry of the pattern, its place in the blocks."""

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


def analyse(indptr: np.ndarray, rows: np.ndarray) -> Layout:
    """The layout of the factors of a lower pattern, and where each of its entries goes in
    the blocks."""
    columns, starts, rowptr, srows = symbolic(indptr, rows)
    widths, heights = np.diff(starts), np.diff(rowptr)
    offsets = np.concatenate([[0], np.cumsum(heights * widths)])
    column_node = np.repeat(np.arange(len(widths)), widths)
    within = np.arange(len(column_node)) - starts[column_node]
    diagonal = offsets[column_node] + within * (heights[column_node] + 1)
    if offsets[-1] >= 2**31:  # the entries' places are 32-bit
        raise ValueError(f"the factor needs {offsets[-1] * 8 / 2**30:.0f} GiB: a coarser lattice or cutoff")
    position = block_positions(indptr, rows, columns, starts, rowptr, srows, offsets)
    return Layout(starts, rowptr, srows, offsets, column_node, diagonal, columns, position)


@numba.njit(nogil=True, cache=True)
def symbolic(indptr, rows):  # pragma: no cover - compiled
    """The supernodal structure of a lower pattern's factor: the columns in the etree's
    postorder (``columns[new] = old``), the relaxed supernodes' first columns ``starts``
    (then the column count), and their rows (``rowptr``, ``rows``)."""
    rowstart, rowcols = lower_rows(indptr, rows)
    parent = elimination_tree(rowstart, rowcols)
    columns = postorder(parent)
    new, up, children = postordered_tree(parent, columns)
    count = column_counts(rowstart, rowcols, columns, new, up)
    first = fundamental_supernodes(up, count, children)
    starts = relaxed_supernodes(first, up, count)
    rowptr, supernode_rows_ = supernode_rows(indptr, rows, columns, new, up, starts)
    return columns, starts, rowptr, supernode_rows_


@numba.njit(nogil=True, cache=True)
def lower_rows(indptr, rows):  # pragma: no cover - compiled
    """The strict lower triangle by rows: row ``i``'s columns ``k < i`` are
    ``rowcols[rowstart[i]:rowstart[i + 1]]``."""
    n = len(indptr) - 1
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
    return rowstart, rowcols


@numba.njit(nogil=True, cache=True)
def elimination_tree(rowstart, rowcols):  # pragma: no cover - compiled
    """Each column's parent in the elimination tree (-1 at a root), by Liu's algorithm with
    path compression."""
    n = len(rowstart) - 1
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
    return parent


@numba.njit(nogil=True, cache=True)
def postorder(parent):  # pragma: no cover - compiled
    """The tree's columns in postorder (children in increasing order, each subtree's
    columns together, descendants before ancestors): ``columns[new] = old``."""
    n = len(parent)
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
    return columns


@numba.njit(nogil=True, cache=True)
def postordered_tree(parent, columns):  # pragma: no cover - compiled
    """The tree in the postorder's numbering: each old column's new one, each new
    column's parent (-1 at a root) and number of children."""
    n = len(parent)
    new = np.empty(n, np.int64)
    new[columns] = np.arange(n)
    up, children = np.full(n, -1, np.int64), np.zeros(n, np.int64)
    for j in range(n):
        if parent[columns[j]] != -1:
            up[j] = new[parent[columns[j]]]
            children[up[j]] += 1
    return new, up, children


@numba.njit(nogil=True, cache=True)
def column_counts(rowstart, rowcols, columns, new, up):  # pragma: no cover - compiled
    """Entries of each column of L (postordered), its diagonal included: row ``i`` of L is
    the part of the tree between the pattern's entries of row ``i`` and ``i`` (its row
    subtree), so each column on it counts ``i`` once."""
    n = len(columns)
    count, mark = np.ones(n, np.int64), np.full(n, -1, np.int64)
    for i in range(n):
        mark[i] = i
        for p in range(rowstart[columns[i]], rowstart[columns[i] + 1]):
            j = new[rowcols[p]]
            while mark[j] != i:
                count[j] += 1
                mark[j] = i
                j = up[j]
    return count


@numba.njit(nogil=True, cache=True)
def fundamental_supernodes(up, count, children):  # pragma: no cover - compiled
    """The first column of each fundamental supernode, then the column count: a column
    starts a new one unless it is the only child of the previous one, which has one entry
    more."""
    n = len(up)
    first = [0]
    for j in range(1, n):
        if not (up[j - 1] == j and count[j - 1] == count[j] + 1 and children[j] == 1):
            first.append(j)
    first.append(n)
    return np.array(first, np.int64)


@numba.njit(nogil=True, cache=True)
def relaxed_supernodes(first, up, count):  # pragma: no cover - compiled
    """The fundamental supernodes ``first`` joined by :data:`NRELAX` / :data:`ZRELAX`:
    supernode ``s`` joins ``s + 1`` (and the ones ``s + 1`` joined) where ``s + 1`` is its
    parent. Returns the first column of each relaxed one, then the column count."""
    nf = len(first) - 1
    width, height, zeros = np.empty(nf, np.int64), np.empty(nf, np.int64), np.zeros(nf)
    joins = np.zeros(nf, np.bool_)
    for s in range(nf):
        width[s], height[s] = first[s + 1] - first[s], count[first[s]]
    for s in range(nf - 2, -1, -1):
        if up[first[s + 1] - 1] != first[s + 1]:
            continue
        own, parents = width[s], width[s + 1]  # s + 1: the supernode it would join, as joined so far
        joined = own + parents
        added = own * (height[s + 1] + own - height[s])  # explicit zeros the join adds
        total = zeros[s + 1] + added
        fraction = total / (joined * (joined + 1) / 2 + joined * (height[s + 1] - parents))
        if (
            joined <= NRELAX[0]
            or added == 0
            or (joined <= NRELAX[1] and fraction < ZRELAX[0])
            or (joined <= NRELAX[2] and fraction < ZRELAX[1])
            or fraction < ZRELAX[2]
        ):
            joins[s] = True
            width[s], height[s], zeros[s] = joined, height[s + 1] + own, total
    bounds = [0]
    s = 0
    while s < nf:  # a supernode: s and those it joined
        while joins[s]:
            s += 1
        s += 1
        bounds.append(first[s])
    return np.array(bounds, np.int64)


@numba.njit(nogil=True, cache=True)
def supernode_rows(indptr, rows, columns, new, up, starts):  # pragma: no cover - compiled
    """Each supernode's rows, sorted: its columns, the pattern's entries below them, and
    its children's rows below them (``rowptr``, ``rows``)."""
    n, ns = len(columns), len(starts) - 1
    node = np.empty(n, np.int64)
    for t in range(ns):
        node[starts[t] : starts[t + 1]] = t
    kids, next_kid = np.full(ns, -1, np.int64), np.full(ns, -1, np.int64)
    mark = np.full(n, -1, np.int64)
    heights, gathered, pieces = np.empty(ns, np.int64), np.empty(n, np.int64), []
    for t in range(ns):
        first, end = starts[t], starts[t + 1]
        found = 0
        for c in range(first, end):
            mark[c] = t
            gathered[found] = c
            found += 1
        for c in range(first, end):
            for p in range(indptr[columns[c]], indptr[columns[c] + 1]):
                i = new[rows[p]]
                if i >= end and mark[i] != t:
                    mark[i] = t
                    gathered[found] = i
                    found += 1
        kid = kids[t]
        while kid != -1:
            for i in pieces[kid]:
                if i >= end and mark[i] != t:
                    mark[i] = t
                    gathered[found] = i
                    found += 1
            kid = next_kid[kid]
        pieces.append(np.sort(gathered[:found]))
        heights[t] = found
        if up[end - 1] != -1:
            q = node[up[end - 1]]
            next_kid[t] = kids[q]
            kids[q] = t
    rowptr = np.zeros(ns + 1, np.int64)
    rowptr[1:] = np.cumsum(heights)
    out = np.empty(rowptr[ns], np.int64)
    for t in range(ns):
        out[rowptr[t] : rowptr[t + 1]] = pieces[t]
    return rowptr, out


@numba.njit(nogil=True, cache=True)
def block_positions(indptr, rows, columns, starts, rowptr, srows, offsets):  # pragma: no cover
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
