from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from bdf.sparse import supernodal, symbolic
from tests.bdf.sparse.test_symbolic import dense_of, random_lower_pattern

KERNELS = ("factor_band", "factorise", "solve", "selected_inverse", "inverse_band")


def factored(indptr, rows, seed):
    """The dense matrix on a random pattern, its layout and its factor's blocks."""
    A = dense_of(indptr, rows, seed)
    layout = symbolic.analyse(indptr, rows)
    values = np.concatenate([A[rows[indptr[j] : indptr[j + 1]], j] for j in range(len(A))])
    blocks = np.zeros(layout.offsets[-1])
    assert supernodal.factor_band(layout, values, np.arange(len(values), dtype=np.int32), 0.0, blocks) == 0
    return A, layout, blocks


def block_of(layout, blocks, s):
    """Supernode ``s``'s rows and its block (rows x columns)."""
    width = layout.starts[s + 1] - layout.starts[s]
    rows = layout.rows[layout.rowptr[s] : layout.rowptr[s + 1]]
    return rows, blocks[layout.offsets[s] : layout.offsets[s + 1]].reshape(width, len(rows)).T


@pytest.mark.parametrize(("n", "density", "seed"), [(60, 0.05, 1), (90, 0.02, 2), (40, 0.3, 3), (30, 0.0, 4)])
def test_factor_solve_and_selected_inverse_equal_dense_algebra_on_random_patterns(n, density, seed):
    """On patterns that are no stencil: L's entries, a solve with several right-hand sides
    and the inverse on the factor's pattern equal numpy's dense Cholesky, solve and inverse
    (in the layout's column order)."""
    indptr, rows = random_lower_pattern(n, density, seed)
    A, layout, blocks = factored(indptr, rows, seed)
    P = layout.columns
    Ap = A[np.ix_(P, P)]
    L, inverse = np.linalg.cholesky(Ap), np.linalg.inv(Ap)
    for s in range(len(layout.starts) - 1):
        R, block = block_of(layout, blocks, s)
        columns = np.arange(layout.starts[s], layout.starts[s + 1])
        lower = R[:, None] >= columns[None, :]
        np.testing.assert_allclose(block[lower], L[np.ix_(R, columns)][lower], rtol=1e-12, atol=1e-14)
    b = np.random.default_rng(seed).standard_normal((n, 3))
    y = b.copy()  # solved in place
    supernodal.solve(layout.rowptr, layout.rows, layout.starts, layout.offsets, blocks, y)
    np.testing.assert_allclose(y, np.linalg.solve(Ap, b), rtol=1e-11, atol=1e-13)
    inv_blocks = blocks.copy()
    info = supernodal.selected_inverse(
        layout.rowptr, layout.rows, layout.starts, layout.offsets, layout.column_node, inv_blocks
    )
    assert info == 0
    for s in range(len(layout.starts) - 1):
        R, block = block_of(layout, inv_blocks, s)
        columns = np.arange(layout.starts[s], layout.starts[s + 1])
        lower = R[:, None] >= columns[None, :]
        np.testing.assert_allclose(block[lower], inverse[np.ix_(R, columns)][lower], rtol=1e-10, atol=1e-13)


def test_the_kernels_release_the_gil_and_give_the_same_answers_side_by_side_in_threads():
    """Every kernel is compiled without the GIL (the classes of a directional map are
    factored in threads), and four factorisations, solves and inversions run at once in
    threads give the serial answers bit for bit (no shared scratch)."""
    for name in KERNELS:
        assert getattr(supernodal, name).targetoptions["nogil"], name
    assert symbolic.symbolic.targetoptions["nogil"]
    patterns = [random_lower_pattern(120, 0.04, seed) for seed in range(4)]

    def work(args):
        (indptr, rows), seed = args
        _, layout, blocks = factored(indptr, rows, seed)
        y = np.ones((len(indptr) - 1, 2))
        supernodal.solve(layout.rowptr, layout.rows, layout.starts, layout.offsets, blocks, y)
        inverse = blocks.copy()
        supernodal.selected_inverse(
            layout.rowptr, layout.rows, layout.starts, layout.offsets, layout.column_node, inverse
        )
        return blocks, y, inverse

    jobs = [(p, seed) for seed, p in enumerate(patterns)] * 3
    serial = [work(job) for job in jobs]
    with ThreadPoolExecutor(4) as pool:
        threaded = list(pool.map(work, jobs))
    for one, other in zip(serial, threaded, strict=True):
        for a, b in zip(one, other, strict=True):
            assert np.array_equal(a, b)
