import numpy as np
import pytest

from bdf import linalg
from bdf.grid import Lattice


@pytest.mark.parametrize(
    ("shape", "cutoff", "idle"), [((9, 8, 5), 1e-3, 0.0), ((30, 28, 3), 1e-6, 0.0), ((12, 10, 4), 1e-4, 0.4)]
)
def test_selected_inverse_equals_the_dense_inverse_on_the_stencil(shape, cutoff, idle):
    """Several supernodes, thin and wide, on a random positive definite band, in the nested
    dissection's order; with a fraction ``idle`` of the hinges untouched by the data (zero
    rows: factored apart), the log-determinant and a solve too."""
    stencil = linalg.stencil(shape, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0), cutoff)
    rng = np.random.default_rng(3)
    band = rng.uniform(-1.0, 1.0, (len(stencil.offsets), stencil.size))
    band[0] = 2.0 * len(stencil.offsets) + rng.uniform(0.0, 1.0, stencil.size)  # dominant diagonal
    untouched = rng.uniform(size=stencil.size) < idle
    for k in range(len(stencil.offsets)):  # a Gram matrix's zero rows and columns
        m, partner = stencil.pairs(k)
        band[k, m[untouched[m] | untouched[partner]]] = 0.0
    factor = stencil.factor_of(band, 0.5)
    assert np.array_equal(factor.support.active, ~untouched)
    assert_dense_algebra(stencil, band, factor, rng)
    # a band touching a few hinges fewer (one class of a map within its total) is
    # factored on the kept support: the extra hinges are decoupled, the answers exact
    fewer = band.copy()
    dropped = ~untouched & (rng.uniform(size=stencil.size) < 0.1)
    for k in range(len(stencil.offsets)):
        m, partner = stencil.pairs(k)
        fewer[k, m[dropped[m] | dropped[partner]]] = 0.0
    assert np.count_nonzero(fewer[0]) * linalg.COVER >= np.count_nonzero(band[0])
    assert stencil.factor_of(fewer, 0.5).support is factor.support
    assert_dense_algebra(stencil, fewer, stencil.factor_of(fewer, 0.5), rng)
    starts = factor.support.layout.starts
    assert len(starts) > 5 and np.diff(starts).max() > 1
    assert np.array_equal(np.sort(stencil.order), np.arange(stencil.size))


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
def test_symbolic_rows_are_the_dense_factors_nonzeros(shape, cutoff, idle, supernodes):
    """Each supernode's rows are exactly the rows of its columns' nonzeros in the dense
    Cholesky factor of a random matrix on the pattern, in the layout's column order (a
    postorder of the elimination tree; idle hinges leave a forest, down to a few lone
    hinges): relaxed supernodes pad their columns with the rows they share, no others."""
    stencil = linalg.stencil(shape, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0), cutoff)
    rng = np.random.default_rng(11)
    active = rng.uniform(size=stencil.size) >= idle
    support = linalg.Support(stencil, active, stencil.order)
    A = support.matrix(rng.uniform(0.5, 1.0, (len(stencil.offsets), stencil.size))).toarray()
    A = A + np.tril(A, -1).T + len(A) * np.eye(len(A))
    layout = linalg._analyse(support._indptr, support._rows)
    P = layout.columns
    L = np.linalg.cholesky(A[np.ix_(P, P)])
    assert len(layout.starts) - 1 >= supernodes
    for s in range(len(layout.starts) - 1):
        f, e = layout.starts[s], layout.starts[s + 1]
        nonzero = np.flatnonzero(np.any(L[:, f:e] != 0.0, axis=1))
        expected = np.union1d(np.arange(f, e), nonzero[nonzero >= f])
        np.testing.assert_array_equal(layout.rows[layout.rowptr[s] : layout.rowptr[s + 1]], expected)
    assert np.array_equal(np.sort(P), np.arange(len(A)))


def assert_dense_algebra(stencil, band, factor, rng):
    """The factor of ``band + 0.5 I``: log-determinant, a solve and the inverse on the
    stencil equal dense algebra's."""
    dense = 0.5 * np.eye(stencil.size)
    for k in range(len(stencil.offsets)):
        m, partner = stencil.pairs(k)
        dense[m, partner] += band[k, m]
        dense[partner, m] += band[k, m] if k else 0.0
    inverse = np.linalg.inv(dense)
    assert factor.logdet() == pytest.approx(np.linalg.slogdet(dense)[1], rel=1e-12)
    b = rng.standard_normal((stencil.size, 2))
    np.testing.assert_allclose(factor.solve(b), np.linalg.solve(dense, b), rtol=1e-10, atol=1e-12)
    got = factor.inverse_band()
    for k in range(len(stencil.offsets)):
        m, partner = stencil.pairs(k)
        np.testing.assert_allclose(got[k, m], inverse[m, partner], rtol=1e-10, atol=1e-14)
        untouched = np.setdiff1d(np.arange(stencil.size), m)
        assert np.all(got[k, untouched] == 0.0)  # partners off the lattice stay zero


def test_band_product_and_midpoint_maps_equal_dense_algebra():
    """``band_product`` (a mode's prior through G) is the dense symmetric product; the
    midpoint maps (G from the data density, the variance density from a band) put each
    pair at its midpoint ``2 idx(m) + o``."""
    stencil = linalg.stencil((7, 6, 4), (1.0, 1.0, 1.0), (1.0, 1.0, 1.0), 1e-3)
    rng = np.random.default_rng(5)
    band = rng.standard_normal((len(stencil.offsets), stencil.size))
    dense = np.zeros((stencil.size, stencil.size))
    mid_shape = tuple(2 * n - 1 for n in stencil.shape)
    density = rng.standard_normal(mid_shape)
    expected_band, expected_density = np.zeros_like(band), np.zeros(mid_shape)
    for k, o in enumerate(stencil.offsets):
        m, partner = stencil.pairs(k)
        dense[m, partner] += band[k, m]
        dense[partner, m] += band[k, m] if k else 0.0
        idx = np.stack(np.unravel_index(m, stencil.shape), axis=1)
        at = tuple((2 * idx + o).T)
        expected_band[k, m] = stencil.factor[k] * density[at]
        np.add.at(expected_density, at, stencil.factor[k] * (2.0 if k else 1.0) * band[k, m])
    x = rng.standard_normal((stencil.size, 3))
    np.testing.assert_allclose(linalg.band_product(stencil, band, x), dense @ x, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(linalg.midpoint_band(stencil, density), expected_band)
    midpoints = Lattice(np.zeros(3), np.full(3, 0.5), mid_shape)
    np.testing.assert_allclose(linalg.band_density(stencil, band, midpoints), expected_density, atol=1e-12)


def test_a_band_that_is_not_positive_definite_raises_on_every_factorisation():
    """The support's first factorisation (after its analysis) and the later ones raise
    NotPositiveDefinite, which the evidence search takes as "more regularisation"; the
    support stays usable."""
    stencil = linalg.stencil((6, 5, 4), (1.0, 1.0, 1.0), (1.0, 1.0, 1.0), 1e-3)
    rng = np.random.default_rng(7)
    band = rng.uniform(-1.0, 1.0, (len(stencil.offsets), stencil.size))
    band[0] = 2.0 * len(stencil.offsets)
    bad = band.copy()
    bad[0, 17] = -1.0  # a negative diagonal entry
    for _ in range(2):
        with pytest.raises(linalg.NotPositiveDefinite):
            stencil.factor_of(bad, 0.5)
    stencil.factor_of(band, 0.5)  # the first good one finds the layout
    with pytest.raises(linalg.NotPositiveDefinite):
        stencil.factor_of(bad, 0.5)
    assert_dense_algebra(stencil, band, stencil.factor_of(band, 0.5), rng)
