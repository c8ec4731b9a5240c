import numpy as np
import pytest

from bdf import linalg


@pytest.mark.parametrize(("shape", "cutoff"), [((9, 8, 5), 1e-3), ((30, 28, 3), 1e-6)])
def test_selected_inverse_equals_the_dense_inverse_on_the_stencil(shape, cutoff):
    """Several supernodes, thin and wide, on a random positive definite band, in the nested
    dissection's order."""
    stencil = linalg.stencil(shape, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0), cutoff)
    rng = np.random.default_rng(3)
    band = rng.uniform(-1.0, 1.0, (len(stencil.offsets), stencil.size))
    band[0] = 2.0 * len(stencil.offsets) + rng.uniform(0.0, 1.0, stencil.size)  # dominant diagonal
    factor = stencil.factor_of(band, 0.5)
    dense = 0.5 * np.eye(stencil.size)
    for k in range(len(stencil.offsets)):
        m, partner = stencil.pairs(k)
        dense[m, partner] += band[k, m]
        dense[partner, m] += band[k, m] if k else 0.0
    inverse = np.linalg.inv(dense)
    got = factor.inverse_band()
    for k in range(len(stencil.offsets)):
        m, partner = stencil.pairs(k)
        np.testing.assert_allclose(got[k, m], inverse[m, partner], rtol=1e-10, atol=1e-14)
        untouched = np.setdiff1d(np.arange(stencil.size), m)
        assert np.all(got[k, untouched] == 0.0)  # partners off the lattice stay zero
    starts = factor._layout().starts
    assert len(starts) > 5 and np.diff(starts).max() > 1
    assert np.array_equal(np.sort(stencil.order), np.arange(stencil.size))
