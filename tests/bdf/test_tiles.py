import itertools

import numpy as np
import pytest

from bdf import BayesianDynamicField, Evidence
from bdf.noise import NOISE_CUTOFF
from bdf.tiles import RegionSpec, key_str, parse_key

PARIS = {
    "name": "paris",
    "origin": {"lat": 48.84, "lon": 2.51, "alt_m": 0.0},
    "bounds_m": {"min": [-40000, -40000, 0], "max": [40000, 40000, 6000]},
    "tile_size_m": [10000, 10000, 6000],
    "overlap_m": [1000, 1000, 0],
    "spacing_m": [1000, 1000, 300],
    "gamma": [5e-7, 5e-7, 5e-6],
    "alpha": "auto",
    "beta": "auto",
}

# a small region: 3 x 2 x 1 tiles of 100 m, 20 m overlap, hinges every 20 m
SMALL = {
    "name": "small",
    "origin": {"lat": 48.0, "lon": 2.0},
    "bounds_m": {"min": [0, 0, 0], "max": [300, 200, 60]},
    "tile_size_m": [100, 100, 60],
    "overlap_m": [20, 20, 0],
    "spacing_m": [20, 20, 20],
    "gamma": [1 / 800, 1 / 800, 1 / 800],
}
#: the same with local noise on a 10 m lattice
LOCAL = {"noise_spacing_m": [10, 10, 10], "noise_prior": 0.5}


def small_flow(X):
    """Steepest at x = 50, 238 and y = 50, 129: inside tiles, so that a border cannot hide
    a jump behind the field's own slope."""
    return np.stack(
        [10 * np.sin((X[:, 0] - 50) / 60), 5 * np.sin((X[:, 1] - 50) / 50), 0.02 * X[:, 2]], axis=1
    )


@pytest.fixture
def small():
    spec = RegionSpec.model_validate(SMALL)
    rng = np.random.default_rng(3)
    X = rng.uniform(spec.lower, spec.upper, (3000, 3))
    V = small_flow(X) + 0.3 * rng.standard_normal(X.shape)
    return spec, X, V


def posteriors(spec, increments):
    return {k: spec.posterior(k, inc.evidence) for k, inc in increments.items()}


def test_spec_json_is_the_service_body():
    spec = RegionSpec.model_validate(PARIS)
    assert spec.model_dump(mode="json") == {
        **PARIS,
        "bounds_m": {"min": [-40000.0, -40000.0, 0.0], "max": [40000.0, 40000.0, 6000.0]},
        "tile_size_m": [10000.0, 10000.0, 6000.0],
        "overlap_m": [1000.0, 1000.0, 0.0],
        "spacing_m": [1000.0, 1000.0, 300.0],
        "noise_spacing_m": None,  # the global noise
        "noise_prior": 0.1,
    }
    assert spec.tile_counts == (8, 8, 1)
    grid = spec.tile_grid((3, 3, 0))
    # grown box [-11000, 1000] per horizontal axis on the region's 1 km lattice, 0..6000 by 300
    assert grid.shape == (13, 13, 21)
    np.testing.assert_allclose(grid.origin, [-11000, -11000, 0])
    assert parse_key(key_str((3, 1, 0))) == (3, 1, 0)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"name": "Paris!"}, "pattern"),
        ({"bounds_m": {"min": [0, 0, 0], "max": [10, -1, 10]}}, "must exceed"),
        ({"overlap_m": [6000, 0, 0]}, "at most half"),
        ({"spacing_m": [10, 10, 10]}, "hinges"),  # 1,201 x 1,201 x 601 in one tile
        ({"gamma": [1, -1, 1]}, "greater than 0"),
        ({"alpha": "aut"}, "alpha"),
        ({"tile_size_m": [100, 100, 100], "overlap_m": [0, 0, 0]}, "tiles"),
        ({"origin": {"lat": 91, "lon": 0}}, "lat"),
        ({"extra": 1}, "extra"),
        ({"noise_spacing_m": [1, 1, 1]}, "noise lattice would have"),
        ({"noise_spacing_m": [10, 10, 10], "noise_prior": 0}, "greater than 0"),
    ],
)
def test_spec_rejects_bad_values(change, message):
    with pytest.raises(ValueError, match=message):
        RegionSpec.model_validate({**PARIS, **change})


def test_points_reach_every_tile_whose_grown_box_holds_them(small):
    spec, X, _ = small
    groups = spec.tiles_containing(X)
    for key in itertools.product(*(range(n) for n in spec.tile_counts)):
        lo, hi = spec.core(key)
        lo, hi = lo - spec.overlap_m, hi + np.array(spec.overlap_m)
        expected = np.flatnonzero(np.all((X >= lo) & (X <= hi), axis=1))
        np.testing.assert_array_equal(np.sort(groups.get(key, [])), expected)
    with pytest.raises(ValueError, match="outside region 'small' bounds: rows \\[1\\]"):
        spec.tiles_containing([[1, 1, 1], [301, 1, 1]])


@pytest.mark.parametrize("local", [{}, LOCAL])
def test_one_tile_region_is_exactly_one_field(small, local):
    _, X, V = small
    one = RegionSpec.model_validate({**SMALL, **local, "tile_size_m": [300, 200, 60]})
    assert one.tile_counts == (1, 1, 1)
    incs = one.increments(X, V)
    mean, std, known = one.predict(X[:50], posteriors(one, incs))
    field = one.tile_field((0, 0, 0)).fit(X, V)
    ref_mean, ref_std = field.predict(X[:50], return_std=True)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(std, ref_std, rtol=1e-10)
    assert known.all()
    assert (field.evidence_.moments is None) == (not local)


def test_increments_are_additive(small):
    spec, X, V = small
    whole = spec.increments(X, V)
    a, b = spec.increments(X[:1000], V[:1000]), spec.increments(X[1000:], V[1000:])
    assert set(whole) == set(a) | set(b)
    for key, inc in whole.items():
        total = a[key].evidence + b[key].evidence
        np.testing.assert_allclose(total.density, inc.evidence.density, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(total.proj, inc.evidence.proj, rtol=1e-12, atol=1e-12)
        assert a[key].points + b[key].points == inc.points
    local = RegionSpec.model_validate({**SMALL, **LOCAL})
    whole = local.increments(X, V)
    a, b = local.increments(X[:1000], V[:1000]), local.increments(X[1000:], V[1000:])
    for key, inc in whole.items():
        total = a[key].evidence + b[key].evidence
        scale = np.abs(inc.evidence.moments).max()
        np.testing.assert_allclose(total.moments, inc.evidence.moments, rtol=1e-9, atol=1e-10 * scale)


def test_weights_are_a_partition_of_unity(small):
    spec, X, _ = small
    total = np.zeros(len(X))
    for key, idx in spec.tiles_containing(X).items():
        total[idx] += spec.tile_weights(key, X[idx])
    np.testing.assert_allclose(total, 1.0, atol=1e-12)


def test_blended_mean_is_continuous_across_borders(small):
    spec, X, V = small
    post = posteriors(spec, spec.increments(X, V))
    rng = np.random.default_rng(0)
    inside, border = [], []
    for _ in range(6):  # lines along x through the borders at x = 100 and 200, and along y (y = 100)
        y, z = rng.uniform(10, 190), rng.uniform(5, 55)
        t = np.arange(0.0, 300.0 + 1e-9, 1.0)
        line = np.stack([t, np.full_like(t, y), np.full_like(t, z)], axis=1)
        jumps = np.abs(np.diff(spec.predict(line, post)[0], axis=0)).max(axis=1)
        near = np.minimum(np.abs(t[:-1] + 0.5 - 100), np.abs(t[:-1] + 0.5 - 200)) < 20
        border.append(jumps[near].max())
        inside.append(jumps[~near].max())
        x = rng.uniform(10, 290)
        t = np.arange(0.0, 200.0 + 1e-9, 1.0)
        line = np.stack([np.full_like(t, x), t, np.full_like(t, z)], axis=1)
        jumps = np.abs(np.diff(spec.predict(line, post)[0], axis=0)).max(axis=1)
        near = np.abs(t[:-1] + 0.5 - 100) < 20
        border.append(jumps[near].max())
        inside.append(jumps[~near].max())
    assert max(border) <= max(inside)
    assert max(inside) < 0.5  # 1 m steps of a field varying on 50-60 m scales


def test_variance_is_the_mixture_variance(small):
    spec, X, V = small
    post = posteriors(spec, spec.increments(X, V))
    x = np.array([[105.0, 50.0, 30.0]])  # overlap of tiles (0,0,0) and (1,0,0)
    mean, std, _ = spec.predict(x, post)
    w = np.array([spec.tile_weights(k, x)[0] for k in [(0, 0, 0), (1, 0, 0)]])
    assert 0 < w[0] < 1 and w.sum() == pytest.approx(1.0)
    parts = [post[k].predict(x, return_std=True) for k in [(0, 0, 0), (1, 0, 0)]]
    mu = sum(wi * m for wi, (m, _) in zip(w, parts, strict=True))
    second = sum(wi * (s**2 + m**2) for wi, (m, s) in zip(w, parts, strict=True))
    np.testing.assert_allclose(mean, mu, rtol=1e-12)
    np.testing.assert_allclose(std, np.sqrt(second - mu**2), rtol=1e-9)


@pytest.mark.parametrize(
    ("upper_x", "local"), [(300.0, {}), (250.0, {}), (250.0, LOCAL)]
)  # 250: the last tiles have fewer hinges
def test_batched_query_equals_tile_by_tile_blending(upper_x, local):
    bounds = {"min": [0, 0, 0], "max": [upper_x, 200, 60]}
    spec = RegionSpec.model_validate({**SMALL, **local, "bounds_m": bounds})
    rng = np.random.default_rng(3)
    X = rng.uniform(spec.lower, spec.upper, (3000, 3))
    V = small_flow(X) + 0.3 * rng.standard_normal(X.shape)
    post = posteriors(spec, spec.increments(X, V))
    assert len({p.grid.shape for p in post.values()}) == (1 if upper_x == 300 else 2)
    q = rng.uniform(spec.lower, spec.upper, (400, 3))
    q[:4, :2] = [[100.0, 100.0], [95.0, 105.0], [100.0, 0.0], [upper_x, 200.0]]  # corners, faces
    total, first, second = np.zeros(len(q)), np.zeros((len(q), 3)), np.zeros((len(q), 3))
    for key, idx in spec.tiles_containing(q).items():  # each tile on its own, plain gathers
        w = spec.tile_weights(key, q[idx])[:, None]
        m, s = post[key].predict(q[idx], return_std=True)
        total[idx] += w[:, 0]
        first[idx] += w * m
        second[idx] += w * (s**2 + m**2)
    mu = first / total[:, None]
    mean, std, known = spec.predict(q, post)
    np.testing.assert_allclose(mean, mu, rtol=1e-10, atol=1e-12 * np.abs(mu).max())
    np.testing.assert_allclose(std, np.sqrt(second / total[:, None] - mu**2), rtol=1e-8)
    assert known.all()
    again = spec.predict(q, post, spec.tiles_containing(q))
    np.testing.assert_array_equal(again[0], mean)
    empty = spec.predict(np.zeros((0, 3)), post)
    assert [a.shape for a in empty] == [(0, 3), (0, 3), (0,)]


def test_tiles_without_data_answer_with_the_prior(small):
    spec, X, V = small
    left = X[:, 0] < 50  # data only in the first tile column, away from its border
    post = posteriors(spec, spec.increments(X[left], V[left]))
    q = np.array([[20.0, 50.0, 30.0], [250.0, 150.0, 30.0]])
    mean, std, known = spec.predict(q, post)
    assert known.tolist() == [True, False]
    np.testing.assert_array_equal(mean[1], 0.0)
    key = (2, 1, 0)
    empty = spec.tile_field(key).set_evidence(Evidence.zeros(spec.tile_grid(key)))
    np.testing.assert_allclose(std[1], empty.predict(q[1:], return_std=True)[1][0], rtol=1e-10)
    # and the tiled answer where data are agrees with a plain field over the same data
    ref = BayesianDynamicField(**{k: v for k, v in spec.tile_field((0, 0, 0)).get_params().items()})
    mine = left & (X[:, 1] <= 120)  # what reached tile (0, 0, 0): its core plus 20 m overlap
    ref.fit(X[mine], V[mine])
    np.testing.assert_allclose(mean[0], ref.predict(q[:1])[0], rtol=1e-10)


def test_with_auto_alpha_tiles_without_data_answer_with_the_region_climatology(small):
    spec, X, V = small
    left = X[:, 0] < 50
    incs = spec.increments(X[left], V[left])
    count = sum(i.evidence.count for i in incs.values())
    v_sq = sum(i.evidence.v_sq for i in incs.values())
    # points counted once per tile that holds them: the mean square over (point, tile) pairs
    pairs = np.concatenate([idx for idx in spec.tiles_containing(X[left]).values()])
    climate = (V[left][pairs] ** 2).mean(axis=0)
    np.testing.assert_allclose(spec.empty_variance(count, v_sq), climate, rtol=1e-12)
    q = np.array([[20.0, 50.0, 30.0], [250.0, 150.0, 30.0], [205.0, 150.0, 30.0]])
    post = posteriors(spec, incs)
    mean, std, known = spec.predict(q, post, empty_variance=climate)
    assert known.tolist() == [True, False, False]
    np.testing.assert_array_equal(mean[1:], 0.0)
    np.testing.assert_allclose(std[1:] ** 2, [climate, climate], rtol=1e-12)  # two empty tiles blend
    # where data are, nothing changes; without data the scale is the data's, not the paper's
    np.testing.assert_array_equal(spec.predict(q[:1], post)[1], std[:1])
    assert not np.allclose(spec.predict(q[1:2], post)[1][0], std[1], rtol=0.5)
    fixed = RegionSpec.model_validate({**SMALL, "alpha": 0.5})
    assert fixed.empty_variance(count, v_sq) is None and spec.empty_variance(0.0, v_sq) is None


def test_stored_blob_round_trips_with_and_without_noisy_points_and_local_noise(small):
    spec, X, V = small
    grid, gamma = spec.tile_grid((0, 0, 0)), np.array(spec.gamma)
    lattice = RegionSpec.model_validate({**SMALL, **LOCAL}).tile_noise_lattice((0, 0, 0))
    noise = np.zeros((50, 3))
    noise[:10] = 4.0  # ten noisy-input points: a dense (packed) Gram part
    for evidence, with_lattice in (
        (Evidence.from_points(grid, gamma, X[:50], V[:50]), None),
        (Evidence.from_points(grid, gamma, X[:50], V[:50], noise), None),
        (Evidence.from_points(grid, gamma, X[:50], V[:50], noise_lattice=lattice), lattice),
        (Evidence.from_points(grid, gamma, X[:50], V[:50], noise, noise_lattice=lattice), lattice),
    ):
        back = Evidence.from_bytes(evidence.to_bytes(), grid, with_lattice)
        assert back.to_arrays().keys() == evidence.to_arrays().keys()
        for name, value in evidence.to_arrays().items():
            np.testing.assert_array_equal(back.to_arrays()[name], value)
        with pytest.raises(ValueError, match="does not fit a grid"):
            Evidence.from_bytes(evidence.to_bytes()[:-8], grid, with_lattice)
        with pytest.raises(ValueError, match="does not fit a grid"):  # read with the other spec
            Evidence.from_bytes(evidence.to_bytes(), grid, lattice if with_lattice is None else None)


@pytest.mark.parametrize(("overlap", "local"), [([20, 20, 0], {}), ([0, 0, 0], {}), ([20, 20, 0], LOCAL)])
def test_grid_prediction_equals_point_prediction(small, overlap, local):
    """The separable grid path against the per-point path, with a tile left empty (prior)."""
    _, X, V = small
    spec = RegionSpec.model_validate({**SMALL, **local, "overlap_m": overlap})
    keep = X[:, 0] < 170  # the tiles (2, *, 0) get no data
    posts = posteriors(spec, spec.increments(X[keep], V[keep]))
    axes = [np.linspace(3, 300, 23), np.linspace(0, 197, 17), np.array([0.0, 31.5, 60.0])]
    mesh = np.stack([m.ravel() for m in np.meshgrid(*axes, indexing="ij")], axis=1)
    for empty in (None, np.array([0.3, 0.2, 0.1])):  # the model's prior, a climatology
        g, p = spec.predict_grid(axes, posts, empty), spec.predict(mesh, posts, None, empty)
        np.testing.assert_allclose(g[1].reshape(-1, 3), p[1], rtol=1e-9 if not local else 20 * NOISE_CUTOFF)
    mean, std, known = spec.predict_grid(axes, posts)
    m, s, k = spec.predict(mesh, posts)
    assert mean.shape == (23, 17, 3, 3) and known.shape == (23, 17, 3)
    assert 0 < (~k).sum() < len(k)  # both data and prior answers are on the grid
    np.testing.assert_allclose(mean.reshape(-1, 3), m, rtol=1e-9, atol=1e-9 * np.abs(m).max())
    # the grid keeps every lattice term; points drop those below a cutoff (NOISE_CUTOFF for moments)
    np.testing.assert_allclose(std.reshape(-1, 3), s, rtol=20 * NOISE_CUTOFF if local else 1e-9)
    np.testing.assert_array_equal(known.ravel(), k)
    with pytest.raises(ValueError, match="inside region"):
        spec.predict_grid([axes[0] + 10, axes[1], axes[2]], posts)
