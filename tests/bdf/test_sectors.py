"""Directional fields: a mixture of heading-sector modes and a share field, still additive."""

import numpy as np
import pytest

from bdf import BayesianDynamicField, metrics
from bdf.crossval import held_out_scores
from bdf.posterior import CLASS_SPREAD_SHARE, LOCAL_PRIOR_HINGES, LOCAL_PRIOR_ROWS, SHARE_FLOOR
from bdf.region.evidence import decode_tile, encode_tile, increments, region_total
from bdf.region.map import RegionMap, compute_posterior, region_field
from bdf.region.spec import RegionSpec
from bdf.sectors import Sectors, mixture_moments
from tests.bdf.conftest import GAMMA, LOWER, SPACING, UPPER, dense_features
from tests.bdf.region.conftest import SMALL
from tests.bdf.test_field import assert_close


@pytest.fixture
def crossing():
    """Two flows through one box: eastbound at 20 m/s everywhere, northbound at 15 m/s in
    its upper half, and a few hovering points (the slow class)."""
    rng = np.random.default_rng(4)
    X = rng.uniform(LOWER, UPPER, (1200, 3))
    V = np.zeros_like(X)
    north = (X[:, 1] > 4) & (rng.random(len(X)) < 0.5)
    V[:, 0] = np.where(north, 0.0, 20.0 + np.sin(X[:, 2]))
    V[:, 1] = np.where(north, 15.0 + np.cos(X[:, 0]), 0.0)
    hover = rng.random(len(X)) < 0.05
    V[hover] = 0.0
    V += 0.3 * rng.standard_normal(V.shape)
    return X, V


def field(S, **kw):
    return BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, "auto", "auto", directions=S, **kw)


def test_sectors_are_centred_on_north_clockwise_and_slow_is_last():
    s = Sectors(4, slow_mps=5.0)
    V = np.array([[0, 10, 0], [10, 0, 0], [0, -10, 0], [-10, 0, 0], [7, 7.2, 0], [1, 1, 9]], float)
    np.testing.assert_array_equal(s.classify(V), [0, 1, 2, 3, 0, 4])
    np.testing.assert_array_equal(s.sector_of_heading([-44, 44, 46, 359, 721]), [0, 0, 1, 0, 0])
    np.testing.assert_array_equal(Sectors(1).classify(V), np.zeros(6))
    for bad in ({"directions": 33}, {"directions": 0}, {"directions": 2.5}, {"slow_mps": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            Sectors(**{"directions": 4, **bad})


def test_one_direction_is_the_paper_model_and_its_one_mode(crossing):
    X, V = crossing
    plain = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, "auto", "auto").fit(X, V)
    one = field(1).fit(X, V)
    Q = np.random.default_rng(1).uniform(LOWER, UPPER, (200, 3))
    mean, std = one.predict(Q, return_std=True)
    np.testing.assert_array_equal(mean, plain.predict(Q))
    modes = one.predict_modes(Q)
    np.testing.assert_array_equal(modes.share, 1.0)
    np.testing.assert_array_equal(modes.mean[:, 0], mean)
    np.testing.assert_array_equal(modes.std[:, 0], std)
    np.testing.assert_array_equal(one.predict(Q, heading_deg=90.0), mean)


def test_a_modes_prior_is_how_its_class_flies_nearby_not_its_layers_average():
    # eastbound at 100 m/s in the west of a wide box and at 200 m/s in its east, a gap far
    # wider than the kernel's reach between them: in the gap each side's mode reverts to
    # its own side's speed (a prior per layer made both 150 m/s, half the flows' gap off)
    rng = np.random.default_rng(5)
    lower, upper = np.zeros(3), np.array([60.0, 10.0, 4.0])
    X = rng.uniform(lower, upper, (3000, 3))
    X = X[(X[:, 0] < 15) | (X[:, 0] > 45)]
    V = np.zeros_like(X)
    V[:, 0] = np.where(X[:, 0] < 30, 100.0, 200.0)
    V += rng.standard_normal(V.shape)
    mix = BayesianDynamicField(lower, upper, 2.0, 0.25, "auto", "auto", directions=4).fit(X, V)
    gap = np.array([[22.0, 5.0, 2.0], [38.0, 5.0, 2.0]])
    modes = mix.predict_modes(gap)
    assert (modes.weight[:, 1] < 1e-3).all()  # no data of its own within the kernel's reach
    np.testing.assert_allclose(modes.mean[:, 1, 0], [100.0, 200.0], atol=10.0)


def test_each_mode_is_the_field_of_its_class_and_the_mixture_is_their_moments(crossing):
    X, V = crossing
    w = np.random.default_rng(2).uniform(0.5, 2.0, len(X))
    mix = field(4).fit(X, V, sample_weight=w)
    post = mix.posterior_
    label = Sectors(4).classify(V)
    assert set(np.unique(label)) == {0, 1, 4}  # north, east, slow
    Q = np.random.default_rng(1).uniform(LOWER, UPPER, (300, 3))
    modes = mix.predict_modes(Q)
    np.testing.assert_array_equal(modes.mean[:, [2, 3]], 0.0)  # no traffic south or west: the prior
    hinges = mix.hinges
    features_sum = np.prod(np.sqrt(np.pi / (GAMMA * SPACING**2)))
    Q_phi = dense_features(Q, hinges, GAMMA)
    for c in (0, 1, 4):
        # the prior weights: at each hinge, the class's Phi^T v over Phi^T 1 over the hinges of
        # its layer within LOCAL_PRIOR_HINGES horizontally, with LOCAL_PRIOR_ROWS observations
        # of the layer's mean, over the features' sum (written out densely here)
        Xc, Vc, wc = X[label == c], V[label == c], w[label == c]
        P = dense_features(Xc, hinges, GAMMA)
        pv, p1 = P.T @ (wc[:, None] * Vc), P.T @ wc
        index = np.round((hinges - hinges.min(axis=0)) / SPACING)
        same_layer = (index[:, None, 2] == index[None, :, 2]).astype(float)
        box = np.abs(index[:, None, :2] - index[None, :, :2]).max(axis=-1) <= LOCAL_PRIOR_HINGES
        layer_mean = (same_layer @ pv) / (same_layer @ p1)[:, None]
        pseudo = LOCAL_PRIOR_ROWS * features_sum
        near = same_layer * box
        w0 = (near @ pv + pseudo * layer_mean) / (near @ p1 + pseudo)[:, None] / features_sum
        # the mode is a field of the class's observations less the prior's field, plus it
        alone = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, post.alpha[1 + c], post.beta[1 + c])
        alone.fit(Xc, Vc - P @ w0, sample_weight=wc)
        mean, std = alone.predict(Q, return_std=True)
        _, epistemic = alone.predict(Q, return_std=True, include_noise=False)
        # widened by the class's spread about its prior mean where the prior holds the mode:
        # the share of its epistemic variance that is the prior's (phi^T phi / alpha inside
        # the lattice)
        prior_share = np.minimum(epistemic**2 * post.alpha[1 + c] / features_sum * 2**1.5, 1.0)
        spread = CLASS_SPREAD_SHARE * (wc @ (Vc - P @ w0) ** 2 / wc.sum())
        assert_close(modes.mean[:, c], mean + Q_phi @ w0, 1e-9, f"mode {c} mean")
        assert_close(modes.std[:, c], np.sqrt(std**2 + prior_share**2 * spread), 1e-9, f"mode {c} std")
        # each mode at its own evidence maximum (to the search's tolerance in nats)
        best = alone.log_evidence_.sum()
        for f in (0.5, 2.0):
            moved = BayesianDynamicField(
                LOWER, UPPER, SPACING, GAMMA, post.alpha[1 + c] * f, post.beta[1 + c]
            )
            moved.fit(Xc, Vc - P @ w0, sample_weight=wc)
            assert moved.log_evidence_.sum() < best + 1.0
    # where no northbound traffic flies, its mode is still northbound (its prior), at about
    # the class's speed (15 m/s; a zero prior gave it ~0 here)
    south = (Q[:, 1] < 2.5) & (np.abs(Q[:, 0] - 5) < 2) & (np.abs(Q[:, 2] - 3) < 1.5)
    assert south.sum() > 5 and (modes.mean[south, 0, 1] > 10).all()
    # the classes with traffic differ from the map with one class and from each other
    ratio = post.alpha[:, 0] / post.beta[:, 0]
    assert len(np.unique(np.round(np.log(ratio[[0, 1, 2]]), 3))) == 3
    # shares: a probability vector everywhere, in the box and far outside it
    far = np.random.default_rng(3).uniform(LOWER - 20, UPPER + 20, (300, 3))
    for P in (Q, far):
        share = mix.predict_modes(P).share
        assert share.shape == (len(P), 5) and (share >= 0).all()
        np.testing.assert_allclose(share.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    # far from the data the shares are the region's overall shares
    overall = np.array([w[label == c].sum() for c in range(5)]) / w.sum()
    np.testing.assert_allclose(mix.predict_modes(UPPER[None] + 100).share[0], overall, atol=1e-9)
    # a class that flies in the region is nowhere certainly absent (the smoother undershoots
    # to negative shares beside the eastbound stream: raised to SHARE_FLOOR of the overall)
    raw = post.prior_share + dense_features(Q, hinges, GAMMA) @ post.share_weights
    assert (raw[:, overall > 0] < 0).any()
    floored = np.maximum(raw, SHARE_FLOOR * overall)
    assert_close(modes.share, floored / floored.sum(axis=1, keepdims=True), 1e-9, "floored shares")
    # where only eastbound traffic flies, the east sector holds nearly all of it
    low = Q[:, 1] < 3
    assert modes.share[low, 1].mean() > 0.85 and modes.share[~low & (Q[:, 1] > 5), 0].mean() > 0.3
    # the mixture's moments are those of its modes
    mean, std = mix.predict(Q, return_std=True)
    ref_mean, ref_std = mixture_moments(modes.share, modes.mean, modes.std)
    assert_close(mean, ref_mean, 1e-12, "mixture mean")
    assert_close(std, ref_std, 1e-12, "mixture std")
    # the conditional for a heading: the two nearest sectors' modes, each one's noise across
    # the heading narrowed by as much as their pool's mean turns with the heading (kappa,
    # here by central differences in the weight, which falls by 1 over the sector's 90
    # degrees), by no more than the spread of headings between the two modes' directions
    # and at most 90 % of it per component, then pooled: precision w / s0^2 +
    # (1 - w) / s1^2, w linear in angle; the mean is the pool of the modes as they are
    rows = np.arange(len(Q))
    noise = [1.0 / m.beta for m in post.modes]  # global noise
    for c in range(5):
        np.testing.assert_array_equal(
            modes.heading_noise[:, c], np.broadcast_to(noise[c] if c < 4 else 0.0, (len(Q), 3))
        )

    def conditional(heading):
        k0, k1, w = (np.broadcast_to(a, len(Q)) for a in Sectors(4).nearest_two(heading))
        (m0, s0), (m1, s1) = ((modes.mean[rows, k], modes.std[rows, k]) for k in (k0, k1))

        def pool(w):
            a0, a1 = w[:, None] / s0**2, (1 - w[:, None]) / s1**2
            return (a0 * m0 + a1 * m1) / (a0 + a1)

        def direction(w):
            return np.arctan2(pool(w)[:, 0], pool(w)[:, 1])

        kappa = -(direction(w + 1e-5) - direction(w - 1e-5)) / 2e-5 / (np.pi / 2)
        kappa = np.clip(kappa, 0, 1)
        # at most the spread of headings uniform between the two modes' directions
        m = pool(w)
        with np.errstate(invalid="ignore"):
            cos_between = (
                (m0[:, :2] * m1[:, :2]).sum(axis=1) / np.hypot(*m0[:, :2].T) / np.hypot(*m1[:, :2].T)
            )
        between = np.where(
            np.isfinite(cos_between), np.arccos(np.clip(cos_between, -1, 1)), 0
        )  # 0: no direction
        spread = (m[:, :2] ** 2).sum(axis=1) * between**2 / 12
        h = np.radians(np.broadcast_to(heading, len(Q)))
        across = np.stack([np.cos(h) ** 2, np.sin(h) ** 2, 0 * h], axis=1)
        variances = []
        for k, s in ((k0, s0), (k1, s1)):
            n = np.stack([noise[i] for i in k])
            told = np.minimum((1 - (1 - kappa) ** 2) * (n * across).sum(axis=1), spread)
            variances.append(s**2 - np.minimum(told[:, None] * across, 0.9 * n))
        std = 1 / np.sqrt(w[:, None] / variances[0] + (1 - w[:, None]) / variances[1])
        plain = 1 / np.sqrt(w[:, None] / s0**2 + (1 - w[:, None]) / s1**2)
        return pool(w), std, plain, kappa

    for heading in (np.where(Q[:, 0] > 5, 90.0, 360.0), 30.0):
        cond_mean, cond_std = mix.predict(Q, return_std=True, heading_deg=heading)
        mean, std, plain, kappa = conditional(heading)
        assert_close(cond_mean, mean, 1e-12, "pooled mean")
        assert_close(cond_std, std, 1e-8, "narrowed, pooled std")
        assert (kappa > 0.2).mean() > 0.2 and (cond_std < 0.9 * plain).any() and (cond_std <= plain).all()
    sector = np.where(Q[:, 0] > 5, 1, 0)
    at_centre = mix.predict(Q, heading_deg=np.where(Q[:, 0] > 5, 90.0, 360.0))
    assert_close(at_centre, modes.mean[rows, sector], 1e-12, "mode at its centre")
    # a held-out row is scored at the heading it flies, or as the slow class below slow_mps
    flying = np.array([[10.0, 10.0 * np.sqrt(3.0), 0.0], [1.0, -1.0, 0.5]] * 150)  # 30 degrees; slow
    flown_mean, flown_std = modes.flown(Sectors(4), flying)
    assert_close(flown_mean[::2], cond_mean[::2], 1e-12, "flown mean")
    assert_close(flown_std[::2], cond_std[::2], 1e-12, "flown std")
    assert_close(flown_mean[1::2], modes.mean[1::2, 4], 1e-12, "slow mean")
    assert_close(flown_std[1::2], modes.std[1::2, 4], 1e-12, "slow std")
    scores = held_out_scores(modes, Sectors(4), flying, V)
    assert scores["cond_rmse"] == pytest.approx(np.sqrt(np.mean((flying - flown_mean) ** 2)), rel=1e-12)
    # continuous in the heading: either side of a sector boundary (45 degrees) the same
    below, above = (mix.predict(Q, return_std=True, heading_deg=h) for h in (45.0 - 1e-9, 45.0 + 1e-9))
    assert_close(below[0], above[0], 1e-6, "mean across a boundary")
    assert_close(below[1], above[1], 1e-6, "std across a boundary")
    with pytest.raises(ValueError, match="heading_deg must be one number or 300"):
        mix.predict(Q, heading_deg=[0.0, 1.0])
    with pytest.raises(ValueError, match="finite"):
        mix.predict(Q, heading_deg=np.nan)


def flows(kind, n, seed):
    """Rows flying one corridor (30 degrees) or every heading, at 15 m/s, scattered by 1 m/s."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(LOWER, UPPER, (n, 3))
    h = np.radians(np.full(n, 30.0) if kind == "corridor" else rng.uniform(0, 360, n))
    V = np.stack([15 * np.sin(h), 15 * np.cos(h), 0.5 * np.sin(X[:, 0])], axis=1)
    return X, V + rng.standard_normal(V.shape)


@pytest.mark.parametrize(
    "kind, S, msll_gain, cov95, plain_cov95",
    [
        ("every heading", 8, (0.15, 0.25), (0.96, 0.975), (0.975, 0.985)),
        ("corridor", 16, (-0.03, 0.0), (0.92, 0.94), (0.94, 0.96)),
    ],
)
def test_a_known_heading_narrows_the_noise_as_far_as_the_pool_follows_it(
    kind, S, msll_gain, cov95, plain_cov95
):
    """Held-out rows scored at their own heading, against the plain pool (``heading_noise``
    zero): where both modes of a heading hold traffic of their sectors (every heading flown)
    the pool turns with the heading and the noise across the track narrows (MSLL 0.20 nats
    better, cov95 0.978 to 0.971); along one corridor crossing a sector boundary the two
    modes point nearly alike and little narrows (cov95 0.951 to 0.930; the sector's width
    spread over the noise, the first rule tried, gives 0.74: ``bench/history/heading-noise-rules.py``).
    Figures at these seeds."""
    X, V = flows(kind, 3000, 0)
    f = field(S).fit(X, V)
    Xt, Vt = flows(kind, 3000, 1)
    modes = f.predict_modes(Xt)
    sectors = Sectors(S)
    narrowed = modes.flown(sectors, Vt)
    plain = modes._replace(heading_noise=np.zeros_like(modes.heading_noise)).flown(sectors, Vt)
    mu, sd = V.mean(0), V.std(0)
    gain = metrics.msll(Vt, *plain, mu, sd) - metrics.msll(Vt, *narrowed, mu, sd)
    assert msll_gain[0] < gain < msll_gain[1]
    assert cov95[0] < metrics.coverage(Vt, *narrowed) < cov95[1]
    assert plain_cov95[0] < metrics.coverage(Vt, *plain) < plain_cov95[1]
    np.testing.assert_array_equal(narrowed[0], plain[0])  # the mean is the plain pool's


@pytest.mark.parametrize("local", [{}, {"noise_spacing": (5.0, 4.0, 3.0)}], ids=["global", "local noise"])
def test_directional_grid_equals_points(crossing, local):
    X, V = crossing
    mix = field(4, **local).fit(X, V)
    axes = [np.linspace(0, 10, 6), np.linspace(1, 7, 4), np.linspace(0, 6, 5)]
    points = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    grid, ref = mix.posterior_.predict_grid_modes(axes), mix.predict_modes(points)
    for name in ("share", "share_std", "mean", "std"):
        got = getattr(grid, name)
        assert_close(got.reshape(len(points), *got.shape[3:]), getattr(ref, name), 1e-9, name)
    mean, var = mix.posterior_.predict_grid(axes)
    ref_mean, ref_std = mix.predict(points, return_std=True)
    assert_close(mean.reshape(-1, 3), ref_mean, 1e-9, "grid mixture mean")
    assert_close(var.reshape(-1, 3), ref_std**2, 1e-9, "grid mixture variance")
    # the compiled moments are those of the modes
    moments = mixture_moments(ref.share, ref.mean, ref.std)
    assert_close(ref_mean, moments[0], 1e-12, "mixture mean")
    assert_close(ref_std, moments[1], 1e-12, "mixture std")
    epistemic = mix.predict_modes(points, include_noise=False)
    moments = mixture_moments(epistemic.share, epistemic.mean, epistemic.std)
    assert_close(mix.posterior_.predict(points, True, include_noise=False)[1], moments[1], 1e-12, "epistemic")


def test_partial_fit_forgetting_and_save_load_per_sector(tmp_path, crossing):
    X, V = crossing
    batch = field(8, half_life=None).fit(X, V)
    sequential = field(8)
    for chunk in np.array_split(np.random.default_rng(0).permutation(len(X)), 3):
        sequential.partial_fit(X[chunk], V[chunk])
    Q = np.random.default_rng(1).uniform(LOWER, UPPER, (100, 3))
    for a, b in zip(batch.predict_modes(Q), sequential.predict_modes(Q), strict=True):
        assert_close(a, b, 1e-9, "sequential vs batch modes")
    batch.save(tmp_path / "mix.npz")
    loaded = BayesianDynamicField.load(tmp_path / "mix.npz")
    assert loaded.directions == 8
    for a, b in zip(batch.predict_modes(Q), loaded.predict_modes(Q), strict=True):
        np.testing.assert_array_equal(a, b)
    # fitted hyperparameters given back as fixed values give the same map
    post = batch.posterior_
    fixed = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, post.alpha, post.beta, directions=8).fit(X, V)
    assert_close(fixed.predict(Q), batch.predict(Q), 1e-9, "fixed hyperparameters")
    with pytest.raises(ValueError, match=r"\(10, 3\)"):
        BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, post.alpha[:5], 1.0, directions=8).fit(X, V)


def test_a_directional_region_is_one_directional_field():
    spec = RegionSpec.model_validate({**SMALL, "directions": 4})
    rng = np.random.default_rng(3)
    X = rng.uniform(spec.lower, spec.upper, (3000, 3))
    V = np.where((X[:, 0] > 150)[:, None], [[0.0, -12.0, 0.0]], [[12.0, 0.0, 0.0]])
    V += 0.5 * rng.standard_normal(V.shape)
    tile_increments = increments(spec, X, V)
    evidence = region_total(spec, {k: i.evidence for k, i in tile_increments.items()})
    post = compute_posterior(spec, evidence)
    ref = region_field(spec, post.alpha, post.beta).fit(X, V)
    Q = rng.uniform(spec.lower, spec.upper, (500, 3))
    mean, std, _ = RegionMap(spec, post).predict(Q)
    ref_mean, ref_std = ref.predict(Q, return_std=True)
    assert_close(mean, ref_mean, 1e-6, "region mixture mean")
    assert_close(std, ref_std, 1e-6, "region mixture std")
    # stored blobs round-trip per class
    key, inc = next(iter(tile_increments.items()))
    half = inc.evidence.scaled(0.5)  # a tile's statistics and residual: their sum is the tile's
    blob = encode_tile(half, half)
    back = decode_tile(spec, key, blob)
    for a, b in zip(back.classes, inc.evidence.classes, strict=True):
        np.testing.assert_array_equal(a.density, b.density)
        np.testing.assert_array_equal(a.mass, b.mass)
    with pytest.raises(ValueError, match=r"cut in class|ends before class"):
        decode_tile(spec, key, blob[:-80])
    with pytest.raises(ValueError, match=r"does not hold its statistics and their residual"):
        decode_tile(spec, key, blob[:40])
