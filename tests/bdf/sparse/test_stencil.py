import numpy as np
import pytest

from bdf.grid import Lattice
from bdf.kernel import Kernel
from bdf.sparse import stencil as sparse_stencil
from bdf.sparse.stencil import NotPositiveDefinite, lattice_stencil


@pytest.mark.parametrize(
    ("shape", "cutoff", "idle"), [((9, 8, 5), 1e-3, 0.0), ((30, 28, 3), 1e-6, 0.0), ((12, 10, 4), 1e-4, 0.4)]
)
def test_selected_inverse_equals_the_dense_inverse_on_the_stencil(shape, cutoff, idle):
    """Several supernodes, thin and wide, on a random positive definite band, in the nested
    dissection's order; with a fraction ``idle`` of the hinges untouched by the data (zero
    rows: factored apart), the log-determinant and a solve too."""
    stencil = lattice_stencil(shape, (1.0, 1.0, 1.0), Kernel((1.0, 1.0, 1.0), cutoff))
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
    assert np.count_nonzero(fewer[0]) * sparse_stencil.COVER >= np.count_nonzero(band[0])
    assert stencil.factor_of(fewer, 0.5).support is factor.support
    assert_dense_algebra(stencil, fewer, stencil.factor_of(fewer, 0.5), rng)
    starts = factor.support.layout.starts
    assert len(starts) > 5 and np.diff(starts).max() > 1
    assert np.array_equal(np.sort(stencil.order), np.arange(stencil.size))


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
    stencil = lattice_stencil((7, 6, 4), (1.0, 1.0, 1.0), Kernel((1.0, 1.0, 1.0), 1e-3))
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
        expected_band[k, m] = stencil.kernel[k] * density[at]
        np.add.at(expected_density, at, stencil.kernel[k] * (2.0 if k else 1.0) * band[k, m])
    x = rng.standard_normal((stencil.size, 3))
    np.testing.assert_allclose(sparse_stencil.band_product(stencil, band, x), dense @ x, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sparse_stencil.midpoint_band(stencil, density), expected_band)
    midpoints = Lattice(np.zeros(3), np.full(3, 0.5), mid_shape)
    np.testing.assert_allclose(
        sparse_stencil.band_density(stencil, band, midpoints), expected_density, atol=1e-12
    )


def test_a_band_that_is_not_positive_definite_raises_on_every_factorisation():
    """The support's first factorisation (after its analysis) and the later ones raise
    NotPositiveDefinite, which the evidence search takes as "more regularisation"; the
    support stays usable."""
    stencil = lattice_stencil((6, 5, 4), (1.0, 1.0, 1.0), Kernel((1.0, 1.0, 1.0), 1e-3))
    rng = np.random.default_rng(7)
    band = rng.uniform(-1.0, 1.0, (len(stencil.offsets), stencil.size))
    band[0] = 2.0 * len(stencil.offsets)
    bad = band.copy()
    bad[0, 17] = -1.0  # a negative diagonal entry
    for _ in range(2):
        with pytest.raises(NotPositiveDefinite):
            stencil.factor_of(bad, 0.5)
    stencil.factor_of(band, 0.5)  # the first good one finds the layout
    with pytest.raises(NotPositiveDefinite):
        stencil.factor_of(bad, 0.5)
    assert_dense_algebra(stencil, band, stencil.factor_of(band, 0.5), rng)


@pytest.mark.parametrize(
    ("shape", "reach"), [((20, 9, 4), (2, 2, 1)), ((17, 17, 3), (3, 2, 3)), ((5, 4, 3), (3, 3, 3))]
)
def test_each_slab_of_the_dissection_separates_its_two_halves(shape, reach):
    """Replaying :func:`dissection`'s recursion: the order is a permutation, each box's two
    halves come before its slab, and no stencil pair within the reach joins a hinge of one
    half to one of the other (a pair inside the box crosses only through the slab), which is
    what keeps the halves' factors apart."""
    order = sparse_stencil.dissection(shape, reach)
    assert np.array_equal(np.sort(order), np.arange(int(np.prod(shape))))
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = np.arange(int(np.prod(shape))).reshape(shape)
    reach = np.array(reach)
    boxes, cuts = [([0, 0, 0], list(shape))], 0
    while boxes:
        lo, hi = boxes.pop()
        extent = np.array(hi) - np.array(lo)
        room = np.where(extent > 2 * reach + 1, extent / reach, 0.0)
        if room.max() == 0:
            continue
        d = int(np.argmax(room))
        c = lo[d] + (extent[d] - reach[d]) // 2
        halves = []
        for a, b in ((lo[d], c), (c + reach[d], hi[d])):
            sub_lo, sub_hi = list(lo), list(hi)
            sub_lo[d], sub_hi[d] = a, b
            boxes.append((sub_lo, sub_hi))
            halves.append(index[tuple(slice(x, y) for x, y in zip(sub_lo, sub_hi, strict=True))].ravel())
        slab_lo, slab_hi = list(lo), list(hi)
        slab_lo[d], slab_hi[d] = c, c + reach[d]
        slab = index[tuple(slice(x, y) for x, y in zip(slab_lo, slab_hi, strict=True))].ravel()
        assert rank[slab].min() > max(rank[halves[0]].max(), rank[halves[1]].max())
        left = np.stack(np.unravel_index(halves[0], shape), axis=1)
        right = np.stack(np.unravel_index(halves[1], shape), axis=1)
        gap = np.abs(left[:, None, d] - right[None, :, d]).min()
        assert gap > reach[d]  # the closest pair across is out of the kernel's reach
        cuts += 1
    assert cuts >= (1 if max(shape) > 2 * max(reach) + 1 else 0)


def test_the_stencil_holds_the_offsets_whose_coupling_is_above_the_cutoff():
    """Offsets o with c(o) = exp(-sum gamma step^2 o^2 / 2) >= cutoff, half of them
    (lexicographically >= 0, zero first), and their couplings as ``kernel``."""
    gamma, step, cutoff = np.array([0.5, 2.0, 1.0]), np.array([1.0, 0.5, 2.0]), 1e-4
    stencil = lattice_stencil((15, 15, 9), tuple(step), Kernel(tuple(gamma), cutoff))
    grid = np.stack(np.meshgrid(*[np.arange(-7, 8)] * 2, np.arange(-4, 5), indexing="ij"), -1).reshape(-1, 3)
    coupling = np.exp(-(grid**2 @ (gamma * step**2)) / 2)
    kept = grid[(coupling >= cutoff) & [tuple(o) >= (0, 0, 0) for o in grid]]
    assert sorted(map(tuple, stencil.offsets)) == sorted(map(tuple, kept))
    assert tuple(stencil.offsets[0]) == (0, 0, 0)
    np.testing.assert_allclose(
        stencil.kernel, np.exp(-(stencil.offsets**2 @ (gamma * step**2)) / 2), rtol=1e-15
    )
