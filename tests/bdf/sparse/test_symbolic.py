import numpy as np
import pytest

from bdf.kernel import Kernel
from bdf.sparse import symbolic
from bdf.sparse.stencil import Support, lattice_stencil


def random_lower_pattern(n: int, density: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A random lower pattern (CSC, sorted, diagonal included) that is no stencil: entries
    anywhere below the diagonal, some columns empty below it."""
    rng = np.random.default_rng(seed)
    dense = np.tril(rng.uniform(size=(n, n)) < density, -1) | np.eye(n, dtype=bool)
    indptr = np.concatenate([[0], np.cumsum(dense.sum(axis=0))]).astype(np.int64)
    rows = np.concatenate([np.flatnonzero(dense[:, j]) for j in range(n)]).astype(np.int32)
    return indptr, rows


def dense_of(indptr, rows, seed: int) -> np.ndarray:
    """A symmetric positive definite matrix on the pattern (diagonally dominant)."""
    n = len(indptr) - 1
    rng = np.random.default_rng(seed)
    A = np.zeros((n, n))
    for j in range(n):
        A[rows[indptr[j] : indptr[j + 1]], j] = rng.uniform(-1.0, 1.0, indptr[j + 1] - indptr[j])
    A = np.tril(A, -1) + np.tril(A, -1).T
    return A + np.diag(np.abs(A).sum(axis=1) + 1.0)


def assert_rows_are_the_factors(layout, A):
    """Each supernode's rows are the rows of its columns' nonzeros in the dense factor of
    ``A`` in the layout's column order: relaxed supernodes pad their columns with the rows
    they share, no others."""
    P = layout.columns
    L = np.linalg.cholesky(A[np.ix_(P, P)])
    for s in range(len(layout.starts) - 1):
        first, end = layout.starts[s], layout.starts[s + 1]
        nonzero = np.flatnonzero(np.any(L[:, first:end] != 0.0, axis=1))
        expected = np.union1d(np.arange(first, end), nonzero[nonzero >= first])
        np.testing.assert_array_equal(layout.rows[layout.rowptr[s] : layout.rowptr[s + 1]], expected)
    assert np.array_equal(np.sort(P), np.arange(len(A)))


@pytest.mark.parametrize(
    ("shape", "cutoff", "idle", "supernodes"),
    [
        ((9, 8, 5), 1e-3, 0.0, 5),
        ((12, 10, 4), 1e-3, 0.5, 5),
        ((20, 4, 3), 1e-2, 0.8, 5),
        ((6, 6, 6), 1e-6, 0.3, 1),  # the kernel's reach spans the lattice: dense
        ((5, 4, 3), 1e-3, 0.95, 1),
    ],
)
def test_supernode_rows_on_stencils_are_the_dense_factors_nonzeros(shape, cutoff, idle, supernodes):
    """On a stencil's support in the nested dissection's order (idle hinges leave a forest,
    down to a few lone hinges)."""
    stencil = lattice_stencil(shape, (1.0, 1.0, 1.0), Kernel((1.0, 1.0, 1.0), cutoff))
    rng = np.random.default_rng(11)
    support = Support(stencil, rng.uniform(size=stencil.size) >= idle, stencil.order)
    A = support.matrix(rng.uniform(0.5, 1.0, (len(stencil.offsets), stencil.size))).toarray()
    A = A + np.tril(A, -1).T + len(A) * np.eye(len(A))
    layout = symbolic.analyse(support._indptr, support._rows)
    assert len(layout.starts) - 1 >= supernodes
    assert_rows_are_the_factors(layout, A)


@pytest.mark.parametrize(("n", "density", "seed"), [(60, 0.05, 1), (90, 0.02, 2), (40, 0.3, 3), (30, 0.0, 4)])
def test_each_step_on_random_patterns_equals_the_dense_factors(n, density, seed):
    """Patterns that are no stencil: the elimination tree is the dense factor's (each
    column's parent is its first nonzero below the diagonal), the postorder keeps
    descendants first, the column counts are the dense factor's, and the supernodes'
    rows are its nonzeros."""
    indptr, rows = random_lower_pattern(n, density, seed)
    A = dense_of(indptr, rows, seed)
    L = np.linalg.cholesky(A)
    rowstart, rowcols = symbolic.lower_rows(indptr, rows)
    parent = symbolic.elimination_tree(rowstart, rowcols)
    for j in range(n):
        below = np.flatnonzero(L[j + 1 :, j] != 0.0)
        assert parent[j] == (j + 1 + below[0] if len(below) else -1)
    columns = symbolic.postorder(parent)
    new, up, children = symbolic.postordered_tree(parent, columns)
    assert np.array_equal(np.sort(columns), np.arange(n))
    assert np.all((up == -1) | (up > np.arange(n)))  # parents after their children
    assert np.array_equal(children, np.bincount(up[up >= 0], minlength=n))
    counts = symbolic.column_counts(rowstart, rowcols, columns, new, up)
    L_post = np.linalg.cholesky(A[np.ix_(columns, columns)])
    np.testing.assert_array_equal(counts, np.count_nonzero(L_post, axis=0))
    first = symbolic.fundamental_supernodes(up, counts, children)
    starts = symbolic.relaxed_supernodes(first, up, counts)
    assert set(starts.tolist()) <= set(first.tolist()) and starts[-1] == n
    layout = symbolic.analyse(indptr, rows)
    np.testing.assert_array_equal(layout.columns, columns)
    np.testing.assert_array_equal(layout.starts, starts)
    assert_rows_are_the_factors(layout, A)
    padded = layout.column_counts()
    assert np.all(padded >= counts)  # relaxed supernodes hold the factor's entries, and zeros
