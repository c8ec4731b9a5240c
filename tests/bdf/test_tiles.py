import numpy as np
import pytest

from bdf import Evidence
from bdf.posterior import KNOWN_WEIGHT
from bdf.region.evidence import increments, region_total
from bdf.region.map import RegionMap, compute_posterior
from bdf.region.spec import RegionSpec, key_str, parse_key
from bdf.sparse import stencil_on
from tests.bdf.conftest import dense_weight

PARIS = {
    "name": "paris",
    "origin": {"lat": 48.84, "lon": 2.51, "alt_m": 0.0},
    "bounds_m": {"min": [-40000, -40000, 0], "max": [40000, 40000, 6000]},
    "tile_size_m": [10000, 10000, 6000],
    "spacing_m": [4000, 4000, 1000],
    "gamma": [5e-7, 5e-7, 5e-6],
    "alpha": "auto",
    "beta": "auto",
}

# a small region: 3 x 2 x 1 tiles of 100 m, hinges every 20 m
SMALL = {
    "name": "small",
    "origin": {"lat": 48.0, "lon": 2.0},
    "bounds_m": {"min": [0, 0, 0], "max": [300, 200, 60]},
    "tile_size_m": [100, 100, 60],
    "spacing_m": [20, 20, 20],
    "gamma": [1 / 400, 1 / 400, 1 / 400],
}
#: the same with local noise on a 10 m lattice
LOCAL = {"noise_spacing_m": [10, 10, 10], "noise_prior": 0.5}


def small_flow(X):
    return np.stack(
        [10 * np.sin((X[:, 0] - 50) / 60), 5 * np.sin((X[:, 1] - 50) / 50), 0.02 * X[:, 2]], axis=1
    )


@pytest.fixture
def small():
    spec = RegionSpec.model_validate(SMALL)
    rng = np.random.default_rng(3)
    # data in the left half only: the right tiles are empty and must revert to the prior
    X = rng.uniform(spec.lower, [150, 200, 60], (3000, 3))
    V = small_flow(X) + 0.3 * rng.standard_normal(X.shape)
    return spec, X, V


def test_spec_json_is_the_service_body():
    spec = RegionSpec.model_validate(PARIS)
    assert spec.model_dump(mode="json") == {
        **PARIS,
        "bounds_m": {"min": [-40000.0, -40000.0, 0.0], "max": [40000.0, 40000.0, 6000.0]},
        "tile_size_m": [10000.0, 10000.0, 6000.0],
        "spacing_m": [4000.0, 4000.0, 1000.0],
        "noise_spacing_m": None,  # the global noise
        "noise_prior": 0.1,
        "cutoff": 1e-12,
        "directions": 1,
        "slow_mps": 5.0,
        "envelope": {  # aircraft
            "max_horizontal_speed_mps": 400.0,
            "max_vertical_speed_mps": 100.0,
            "max_input_noise_std_m": 1000.0,
            "min_sample_weight": 1e-06,
            "max_sample_weight": 1000.0,
        },
    }
    assert spec.tile_counts == (8, 8, 1)
    assert spec.grid.shape == (21, 21, 7)  # the Paris core lattice, 3,087 hinges
    grid = spec.tile_grid((3, 3, 0))
    # core [-10000, 0] grown by the kernel's reach at the cutoff (7.4 km), on the 4 km lattice
    np.testing.assert_allclose(grid.origin, [-16000, -16000, 0])
    assert grid.shape == (6, 6, 7)
    assert parse_key(key_str((3, 1, 0))) == (3, 1, 0)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"name": "Paris!"}, "pattern"),
        ({"bounds_m": {"min": [0, 0, 0], "max": [10, -1, 10]}}, "must exceed"),
        ({"spacing_m": [100, 100, 100]}, "hinges"),  # 801 x 801 x 61 in the region
        ({"gamma": [1, -1, 1]}, "greater than 0"),
        ({"alpha": "aut"}, "alpha"),
        ({"tile_size_m": [100, 100, 100]}, "tiles"),
        ({"origin": {"lat": 91, "lon": 0}}, "lat"),
        ({"extra": 1}, "extra"),
        ({"cutoff": 1}, "less than 1"),
        ({"directions": 17}, "less than or equal to 16"),
        ({"directions": 0}, "greater than or equal to 1"),
        ({"overlap_m": [1000, 1000, 0]}, "extra"),  # tiles no longer overlap
        ({"noise_spacing_m": [100, 100, 100]}, "noise lattice would have"),
        ({"noise_spacing_m": [1000, 1000, 100], "noise_prior": 0}, "greater than 0"),
    ],
)
def test_spec_rejects_bad_values(change, message):
    with pytest.raises(ValueError, match=message):
        RegionSpec.model_validate({**PARIS, **change})


def test_each_observation_is_counted_once_and_the_tiles_sum_to_the_region(small):
    spec, X, V = small
    w = np.random.default_rng(1).uniform(0.5, 2.0, len(X))
    tile_increments = increments(spec, X, V, sample_weight=w)
    assert sum(i.points for i in tile_increments.values()) == len(X)
    assert sum(i.evidence.count for i in tile_increments.values()) == pytest.approx(w.sum(), rel=1e-12)
    (total,) = region_total(spec, {k: i.evidence for k, i in tile_increments.items()}).classes
    direct = Evidence.from_points(spec.grid, spec.kernel, X, V, sample_weight=w, mass=False)
    for name in ("density", "proj", "mass", "v_sum", "v_sq"):
        got, want = getattr(total, name), getattr(direct, name)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())


@pytest.mark.parametrize("local", [{}, LOCAL, {"cutoff": 1e-6}])  # a looser cutoff: smaller tiles
@pytest.mark.parametrize("alpha", ["auto", 2.0])
def test_the_region_is_one_field_everywhere_empty_places_included(small, local, alpha):
    spec = RegionSpec.model_validate({**SMALL, **local, "alpha": alpha})
    _, X, V = small
    tile_increments = increments(spec, X, V)
    post = compute_posterior(spec, region_total(spec, {k: i.evidence for k, i in tile_increments.items()}))
    field = spec.field(post.alpha, post.beta).fit(X, V)
    Q = np.random.default_rng(2).uniform(spec.lower, spec.upper, (2000, 3))
    mean, std, known = RegionMap(spec, post).predict(Q)
    ref_mean, ref_std = field.predict(Q, return_std=True)
    climate = np.sqrt((V**2).mean(0))
    np.testing.assert_allclose(mean, ref_mean, rtol=0, atol=1e-6 * climate.min())
    np.testing.assert_allclose(std, ref_std, rtol=1e-6)
    # the right third of the region has no data within the kernel's reach
    assert known[Q[:, 0] < 150].all() and not known[Q[:, 0] > 260].any()
    np.testing.assert_array_equal(known, post.data_weight(Q)[:, 0] >= KNOWN_WEIGHT)
    # the grid path equals the point path
    axes = [np.linspace(0, 300, 7), np.linspace(0, 200, 5), np.array([10.0, 50.0])]
    g_mean, g_std, g_known = RegionMap(spec, post).predict_grid(axes)
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    p_mean, p_std, p_known = RegionMap(spec, post).predict(mesh)
    np.testing.assert_allclose(g_mean.reshape(-1, 3), p_mean, rtol=0, atol=1e-9 * climate.min())
    np.testing.assert_allclose(g_std.reshape(-1, 3), p_std, rtol=1e-9)
    np.testing.assert_array_equal(g_known.ravel(), p_known)


@pytest.mark.parametrize("directions", [1, 4])
def test_known_is_where_the_data_weigh_within_the_kernels_reach(small, directions):
    """The data's weight within the kernel's reach, from their density, against the direct
    sum over the observations: to 0.5 % inside, overstated by at most 2 per face of the
    lattice near it (the midpoint of a point and an observation further in sees more of
    the lattice); each class's own for a directional map; the grid path equals the points'.
    ``known`` follows it, not the tiles: a corner of a tile with data, far from them, is
    not known."""
    spec = RegionSpec.model_validate({**SMALL, "directions": directions})
    _, X, V = small
    rng = np.random.default_rng(5)
    w = rng.uniform(0.001, 0.01, len(X))
    tile_increments = increments(spec, X, V, sample_weight=w)
    post = compute_posterior(spec, region_total(spec, {k: i.evidence for k, i in tile_increments.items()}))
    Q = rng.uniform(spec.lower, spec.upper, (1500, 3))
    gamma = np.array(spec.gamma)
    label = spec.sectors.classify(V)
    got = post.data_weight(Q)
    assert got.shape == (len(Q), spec.sectors.classes)
    inside = np.all((Q > spec.lower + gamma**-0.5) & (Q < spec.upper - gamma**-0.5), axis=1)
    for c in range(spec.sectors.classes):
        want = dense_weight(X[label == c], Q, gamma, w[label == c])
        seen = want > 1e-6
        ratio = got[seen, c] / want[seen]
        assert np.abs(ratio[inside[seen]] - 1).max() < 5e-3
        assert ratio.min() > 0.95 and ratio.max() < 8.0
    axes = [np.linspace(0, 300, 7), np.linspace(0, 200, 5), np.array([10.0, 50.0])]
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    np.testing.assert_allclose(
        post.data_weight_grid(axes).reshape(len(mesh), -1), post.data_weight(mesh), rtol=1e-9, atol=1e-12
    )
    _, _, known = RegionMap(spec, post).predict(Q)
    np.testing.assert_array_equal(known, got.sum(1) >= KNOWN_WEIGHT)
    # the far corner of tile (1, 1, 0), whose core holds data up to x = 150, is not known
    corner = np.array([[199.0, 199.0, 30.0]])
    assert (1, 1, 0) in tile_increments and not RegionMap(spec, post).predict(corner)[2][0]


def test_stored_blob_round_trips_with_and_without_noisy_points_and_local_noise(small):
    spec, X, V = small
    local = RegionSpec.model_validate({**SMALL, **LOCAL})
    grid, kernel = spec.tile_grid((0, 0, 0)), spec.kernel
    stencil, lattice = stencil_on(grid, kernel), local.tile_noise_lattice((0, 0, 0))
    noise = np.zeros((50, 3))
    noise[:10] = 4.0  # ten noisy-input points: a Gram band
    for evidence, with_lattice in (
        (Evidence.from_points(grid, kernel, X[:50], V[:50]), None),
        (Evidence.from_points(grid, kernel, X[:50], V[:50], noise), None),
        (Evidence.from_points(grid, kernel, X[:50], V[:50], noise_lattice=lattice), lattice),
        (Evidence.from_points(grid, kernel, X[:50], V[:50], noise, noise_lattice=lattice), lattice),
    ):
        back = Evidence.from_bytes(evidence.to_bytes(), grid, stencil, with_lattice)
        assert back.to_arrays().keys() == evidence.to_arrays().keys()
        for name, value in evidence.to_arrays().items():
            np.testing.assert_array_equal(back.to_arrays()[name], value)
        with pytest.raises(ValueError, match="does not fit a grid"):
            Evidence.from_bytes(evidence.to_bytes()[:-8], grid, stencil, with_lattice)
        with pytest.raises(ValueError, match="does not fit a grid"):  # read with the other spec
            Evidence.from_bytes(evidence.to_bytes(), grid, stencil, lattice if with_lattice is None else None)


def test_noisy_inputs_in_tiles_equal_the_field(small):
    spec, X, V = small
    noise = np.full((len(X), 3), 3.0)
    tile_increments = increments(spec, X, V, input_noise_std=noise)
    spec = spec.model_copy(update={"alpha": 1.0, "beta": 5.0})
    post = compute_posterior(spec, region_total(spec, {k: i.evidence for k, i in tile_increments.items()}))
    field = spec.field().fit(X, V, input_noise_std=noise)
    Q = np.random.default_rng(4).uniform(spec.lower, spec.upper, (500, 3))
    mean, std, _ = RegionMap(spec, post).predict(Q)
    ref_mean, ref_std = field.predict(Q, return_std=True)
    np.testing.assert_allclose(mean, ref_mean, rtol=0, atol=1e-6 * np.abs(ref_mean).max())
    np.testing.assert_allclose(std, ref_std, rtol=1e-6)
