import numpy as np
import pytest

from bdf.posterior import KNOWN_WEIGHT
from bdf.region.evidence import increments, region_total
from bdf.region.map import RegionMap, compute_posterior, region_field
from bdf.region.spec import RegionSpec
from tests.bdf.conftest import dense_weight
from tests.bdf.region.conftest import LOCAL, SMALL


@pytest.mark.parametrize("local", [{}, LOCAL, {"cutoff": 1e-6}])  # a looser cutoff: smaller tiles
@pytest.mark.parametrize("alpha", ["auto", 2.0])
def test_the_region_is_one_field_everywhere_empty_places_included(small, local, alpha):
    spec = RegionSpec.model_validate({**SMALL, **local, "alpha": alpha, "model_directions": 1})
    _, X, V = small
    tile_increments = increments(spec, X, V)
    post = compute_posterior(spec, region_total(spec, {k: i.evidence for k, i in tile_increments.items()}))
    field = region_field(spec, post.alpha, post.beta).fit(X, V)
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
    spec = RegionSpec.model_validate({**SMALL, "directions": directions, "model_directions": directions})
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
        post.predict_grid_modes(axes).weight.reshape(len(mesh), -1),
        post.data_weight(mesh),
        rtol=1e-9,
        atol=1e-12,
    )
    _, _, known = RegionMap(spec, post).predict(Q)
    np.testing.assert_array_equal(known, got.sum(1) >= KNOWN_WEIGHT)
    # the far corner of tile (1, 1, 0), whose core holds data up to x = 150, is not known
    corner = np.array([[199.0, 199.0, 30.0]])
    assert (1, 1, 0) in tile_increments and not RegionMap(spec, post).predict(corner)[2][0]


def test_noisy_inputs_in_tiles_equal_the_field(small):
    spec, X, V = small
    noise = np.full((len(X), 3), 3.0)
    tile_increments = increments(spec, X, V, input_noise_std=noise)
    spec = spec.model_copy(update={"alpha": 1.0, "beta": 5.0})
    post = compute_posterior(spec, region_total(spec, {k: i.evidence for k, i in tile_increments.items()}))
    field = region_field(spec).fit(X, V, input_noise_std=noise)
    Q = np.random.default_rng(4).uniform(spec.lower, spec.upper, (500, 3))
    mean, std, _ = RegionMap(spec, post).predict(Q)
    ref_mean, ref_std = field.predict(Q, return_std=True)
    np.testing.assert_allclose(mean, ref_mean, rtol=0, atol=1e-6 * np.abs(ref_mean).max())
    np.testing.assert_allclose(std, ref_std, rtol=1e-6)


def test_one_class_answers_the_moments_of_its_models_mixture(small):
    """A region of one class on 8 sectors learns what the region of 8 sectors learns and
    answers what it answers without a heading (the mixture's moments), at points and on
    grids; its one mode is those moments with share 1 and all the data's weight; a heading
    changes nothing."""
    _, X, V = small
    one_spec, eight_spec = (RegionSpec.model_validate({**SMALL, "directions": d}) for d in (1, 8))
    assert one_spec.model_directions == 8
    evidence = [
        region_total(spec, {k: i.evidence for k, i in increments(spec, X, V).items()})
        for spec in (one_spec, eight_spec)
    ]
    for a, b in zip(*(e.classes for e in evidence), strict=True):
        np.testing.assert_array_equal(a.proj, b.proj)
        np.testing.assert_array_equal(a.density, b.density)
    post = compute_posterior(one_spec, evidence[0])
    one, eight = RegionMap(one_spec, post), RegionMap(eight_spec, post)
    Q = np.random.default_rng(4).uniform(one.spec.lower, one.spec.upper, (500, 3))
    for got, want in zip(one.predict(Q), eight.predict(Q), strict=True):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(one.predict(Q, heading_deg=90.0)[0], one.predict(Q)[0])
    modes, full = one.predict_modes(Q), eight.predict_modes(Q)
    assert modes.share.shape == (len(Q), 1) and np.all(modes.share == 1)
    for got, want in zip((modes.mean[:, 0], modes.std[:, 0]), eight.predict(Q)[:2], strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(modes.weight[:, 0], full.weight.sum(axis=1), rtol=1e-12)
    axes = [np.linspace(0, 300, 7), np.linspace(0, 200, 5), np.array([10.0, 50.0])]
    for got, want in zip(one.predict_grid(axes), eight.predict_grid(axes), strict=True):
        np.testing.assert_array_equal(got, want)
    grid_modes = one.predict_grid_modes(axes)
    assert grid_modes.share.shape == (7, 5, 2, 1)
    np.testing.assert_allclose(
        grid_modes.mean[..., 0, :], eight.predict_grid(axes)[0], rtol=1e-12, atol=1e-12
    )


def test_a_stored_posterior_is_read_back_only_by_the_model_revision_that_stored_it(small, monkeypatch):
    """A stored map is the model's at its revision: read back equal by the same code; one
    stored by another revision (or before revisions were stored) is refused, so the service
    computes it again instead of serving an older model's map."""
    import pickle

    from bdf.region import map as region_map

    _, X, V = small
    spec = RegionSpec.model_validate({**SMALL, "directions": 4})
    post = compute_posterior(
        spec, region_total(spec, {k: i.evidence for k, i in increments(spec, X, V).items()})
    )
    blob = region_map.encode_posterior(post)
    Q = np.random.default_rng(5).uniform(spec.lower, spec.upper, (50, 3))
    for got, want in zip(
        RegionMap(spec, region_map.decode_posterior(blob)).predict(Q),
        RegionMap(spec, post).predict(Q),
        strict=True,
    ):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="model revision None"):
        region_map.decode_posterior(pickle.dumps(post, protocol=5))  # as stored before revisions
    stored = region_map.MODEL_REVISION
    monkeypatch.setattr(region_map, "MODEL_REVISION", stored + 1)
    with pytest.raises(ValueError, match=f"model revision {stored}, not this code's {stored + 1}"):
        region_map.decode_posterior(blob)
