"""The two gather paths (compiled point by point, and BLAS by blocks) against each other
and against the dense sum; the splat against the dense sum."""

from unittest import mock

import numba
import numpy as np
import pytest

from bdf import features
from bdf.grid import Lattice


def _options(kernel) -> dict:
    return {k: v for k, v in kernel.targetoptions.items() if k not in ("nopython", "boundscheck")}


#: The compiled kernels' source with bounds checks (and their other options: the same
#: rounding): an index that leaves its arrays raises.
BOUNDS_CHECKED = {
    name: numba.njit(**_options(getattr(features, name)), boundscheck=True)(getattr(features, name).py_func)
    for name in (
        "_gather_lanes",
        "_sort_blocks",
        "_splat_blocks",
        "_splat_rows",
        "_axis_factors",
        "_window_exponents",
    )
}


def dense_factors(lattice, X, k, cutoff):
    """Per point, its factor at every lattice point of each axis, below the cutoff zeroed."""
    k = np.broadcast_to(np.asarray(k, float).reshape(-1, 3), (len(X), 3))
    for n, x in enumerate(X):
        f = [np.exp(-k[n, d] * (x[d] - lattice.axis(d)) ** 2) for d in range(3)]
        yield [np.where(fd < cutoff, 0.0, fd) for fd in f]


def dense_gather(lattice, X, T, k, cutoff):
    """The sum written out: every lattice point, per-axis factors below the cutoff zeroed."""
    out = np.zeros((len(X), T.shape[-1]))
    for n, f in enumerate(dense_factors(lattice, X, k, cutoff)):
        out[n] = np.einsum("i,j,k,ijkc->c", *f, T)
    return out


@pytest.mark.parametrize("cutoff", [1e-12, 1e-6])
@pytest.mark.parametrize("per_point_k", [False, True])
@pytest.mark.parametrize("channels", [1, 3, 10])
@pytest.mark.parametrize("layers", [9, 2])  # 2: rows (z and channels) shorter than the kernel's chunk
@pytest.mark.parametrize("lanes", features.LANE_WIDTHS)
def test_pointwise_gather_equals_the_blocked_gather_and_the_dense_sum(
    cutoff, per_point_k, channels, layers, lanes
):
    """300 points: blocks of :data:`features.BLOCK_POINTS` and a part of one."""
    rng = np.random.default_rng(channels)
    lattice = Lattice(np.array([-100.0, 50.0, 0.0]), np.array([40.0, 30.0, 25.0]), (23, 17, layers))
    T = rng.standard_normal((*lattice.shape, channels))
    lo, hi = lattice.origin, lattice.origin + lattice.step * (np.array(lattice.shape) - 1)
    X = rng.uniform(lo - 60, hi + 60, (300, 3))  # some points outside the lattice
    X[:5] = lattice.points()[[0, 7, 100, 700, -1]]  # some exactly on lattice points
    X[5:8] = [[-1e4, 100, 50], [200, 1e5, 50], [200, 100, -1e3]]  # beyond every lattice point's reach
    k = (1.0 / lattice.step**2) * (rng.uniform(0.5, 2.0, (len(X), 3)) if per_point_k else 1.0)
    table = features.LaneTable.of(T, lanes)
    pointwise = features.gather_pointwise(lattice, X, table, k, cutoff=cutoff)
    blocked = features.gather_blocked(lattice, X, T, k, cutoff=cutoff)
    scale = np.abs(blocked).max()
    assert np.abs(pointwise - blocked).max() <= 1e-12 * scale
    assert np.abs(pointwise - dense_gather(lattice, X, T, k, cutoff)).max() <= 1e-12 * scale
    with mock.patch.multiple(features, **BOUNDS_CHECKED):
        checked = features.gather_pointwise(lattice, X, table, k, cutoff=cutoff)
    np.testing.assert_array_equal(checked, pointwise)


def dense_splat(lattice, X, W, k, cutoff):
    """``T[g, c] = sum_n W[n, c] w(x_n, g)`` written out (per-axis factors below the cutoff zeroed)."""
    out = np.zeros((*lattice.shape, W.shape[1]))
    for n, f in enumerate(dense_factors(lattice, X, k, cutoff)):
        out += np.einsum("i,j,k,c->ijkc", *f, W[n])
    return out


@pytest.mark.parametrize("cutoff", [1e-12, 1e-6])
@pytest.mark.parametrize("per_point_k", [False, True])
@pytest.mark.parametrize(("points", "block"), [(3000, 1), (300, 1), (300, 2), (40, 1), (3000, 32)])
def test_splat_equals_the_dense_sum(cutoff, per_point_k, points, block):
    """Many blocks of one cell, blocks that grow (300 points are too few for blocks of one
    cell), blocks of two, one window (too few points to sort), one block of many chunks
    (:data:`~bdf.features.SPLAT_CHUNK`): every path of the blocking, also with bounds checks
    on the compiled kernels."""
    rng = np.random.default_rng(points)
    lattice = Lattice(np.array([-100.0, 50.0, 0.0]), np.array([40.0, 30.0, 25.0]), (23, 17, 9))
    lo, hi = lattice.origin, lattice.origin + lattice.step * (np.array(lattice.shape) - 1)
    X = rng.uniform(lo - 60, hi + 60, (points, 3))  # some points outside the lattice
    X[:5] = lattice.points()[[0, 7, 100, 700, -1]]  # some exactly on lattice points
    W = rng.standard_normal((points, 4))
    k = (1.0 / lattice.step**2) * (rng.uniform(0.5, 2.0, (points, 3)) if per_point_k else 1.0)
    splat = features.splat(lattice, X, W, k, cutoff=cutoff, block=block)
    dense = dense_splat(lattice, X, W, k, cutoff)
    assert np.abs(splat - dense).max() <= 1e-12 * np.abs(dense).max()
    with mock.patch.multiple(features, **BOUNDS_CHECKED):
        checked = features.splat(lattice, X, W, k, cutoff=cutoff, block=block)
    np.testing.assert_allclose(checked, splat, rtol=0, atol=1e-13 * np.abs(dense).max())


def test_gather_takes_the_pointwise_path_for_queries_and_blocks_above():
    rng = np.random.default_rng(0)
    lattice = Lattice(np.zeros(3), np.ones(3), (12, 12, 6))
    T = rng.standard_normal((*lattice.shape, 10))
    k = np.ones(3)
    for n in (features.POINTWISE_MAX_POINTS, features.POINTWISE_MAX_POINTS + 1):
        X = rng.uniform(0, 11, (n, 3))
        got = features.gather(lattice, X, T, k)
        path = features.gather_pointwise if n <= features.POINTWISE_MAX_POINTS else features.gather_blocked
        np.testing.assert_array_equal(got, path(lattice, X, T, k))
    assert features.gather(lattice, np.empty((0, 3)), T, k).shape == (0, 10)


@pytest.mark.parametrize("lanes", features.LANE_WIDTHS)
@pytest.mark.parametrize(("layers", "channels"), [(1, 1), (3, 5), (6, 3), (9, 10)])
def test_a_lane_table_holds_the_lattice_values_and_gathers_as_they_do(layers, channels, lanes):
    """Rows of 1, 15, 18 and 90 values (one chunk and more, a last chunk of a few values):
    the padding of the last chunk never reaches an answer, and the table gives back the
    values it was made of."""
    rng = np.random.default_rng(layers)
    lattice = Lattice(np.zeros(3), np.ones(3), (7, 5, layers))
    T = rng.standard_normal((*lattice.shape, channels))
    table = features.LaneTable.of(T, lanes)
    assert table.shape == T.shape and table.values.shape[-1] == lanes
    np.testing.assert_array_equal(table.array(), T)
    X = rng.uniform(-2, 8, (200, 3))
    assert (
        np.abs(
            features.gather_pointwise(lattice, X, table, k=np.ones(3))
            - dense_gather(lattice, X, T, np.ones(3), 1e-12)
        ).max()
        <= 1e-12 * np.abs(T).max()
    )


@pytest.mark.parametrize("channels", [1, 3, 36])
def test_grid_gather_equals_the_dense_sum(channels):
    rng = np.random.default_rng(channels)
    lattice = Lattice(np.array([-100.0, 50.0, 0.0]), np.array([40.0, 30.0, 25.0]), (9, 7, 5))
    T = rng.standard_normal((*lattice.shape, channels))
    axes = [np.linspace(-150, 300, 11), np.linspace(20, 260, 6), np.linspace(-10, 120, 4)]
    k = 1.0 / lattice.step**2
    got = features.gather_grid(lattice, axes, T, k, cutoff=1e-6)
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    want = dense_gather(lattice, mesh, T, k, 1e-6).reshape(got.shape)
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    for lanes in features.LANE_WIDTHS:
        got = features.gather_grid(lattice, axes, features.LaneTable.of(T, lanes), k, cutoff=1e-6)
        assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()


def test_lane_tables_are_as_wide_as_a_window_plane_in_l1_allows():
    """32 values on the hinge lattice at ``gamma = 1 / spacing^2`` (11 x 11 columns of a
    window, 31 KB), 16 on its midpoint lattice (15 x 15: 58 KB at 32), 16 for the widest
    window of per-point scales; a table of another width is refused."""
    lattice = Lattice(np.zeros(3), np.full(3, 100.0), (41, 41, 8))
    gamma = 1.0 / lattice.step**2
    assert features.lanes_for(lattice, gamma, 1e-12) == 32
    midpoints = Lattice(lattice.origin, lattice.step / 2.0, (81, 81, 15))
    assert features.lanes_for(midpoints, 2.0 * gamma, 1e-12) == 16
    assert features.lanes_for(lattice, np.stack([gamma, gamma / 4]), 1e-12) == 16
    with pytest.raises(ValueError, match="16, 32"):
        features.LaneTable.of(np.zeros((2, 2, 2, 1)), 8)
