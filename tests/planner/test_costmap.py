"""The cost map against analytic fields: interpolation, segment integrals, metrics, boxes."""

import numpy as np
import pytest
from scipy.stats import norm

from bdf import BayesianDynamicField
from bdf.sectors import Sectors
from planner.costmap import CURVATURE_SAFETY, CostMap, CostWeights, ModeGrids, path_metrics
from planner.search import Box, PlanningProblem

AXES = (np.linspace(0, 1000, 21), np.linspace(-500, 500, 11), np.linspace(0, 300, 7))


def mesh():
    return np.stack(np.meshgrid(*AXES, indexing="ij"), -1)


def costmap(std_fn, mean=(0.0, 0.0, 0.0), **weights):
    G = mesh()
    std = np.repeat(std_fn(G)[..., None], 3, -1)
    mean = np.broadcast_to(np.asarray(mean, float), std.shape)
    return CostMap(AXES, mean, std, CostWeights(**{"max_std_mps": 2.0, **weights}))


def random_points(n, seed=0):
    return np.random.default_rng(seed).uniform([0, -500, 0], [1000, 500, 300], (n, 3))


def test_trilinear_interpolation_is_exact_for_linear_fields_and_bounded_for_quadratic():
    cm = costmap(lambda G: 1 + 0.002 * G[..., 0] - 0.001 * G[..., 1] + 0.003 * G[..., 2])
    X = random_points(500)
    expected = 1 + 0.002 * X[:, 0] - 0.001 * X[:, 1] + 0.003 * X[:, 2]
    np.testing.assert_allclose(cm.max_std(X), expected, rtol=1e-12)
    # f = a x^2: error |f''| h^2 / 8 = a h^2 / 4 at most (h = 50 m), reached mid-cell
    a = 1e-5
    cm = costmap(lambda G: 1 + a * G[..., 0] ** 2)
    err = np.abs(cm.max_std(X) - (1 + a * X[:, 0] ** 2))
    assert a * 50**2 / 4 * 0.95 < err.max() <= a * 50**2 / 4 + 1e-12


def test_the_hard_tube_bound_is_exact_for_concave_quadratics_and_never_below_smooth_fields():
    X = random_points(2000)
    a, b = 2e-6, 2e-5
    # s = 5 - a x^2 - b z^2: concave, constant second differences: the bound is the
    # interpolation plus its exact error, times the safety factor
    cm = costmap(lambda G: 5 - a * G[..., 0] ** 2 - b * G[..., 2] ** 2)
    exact = 5 - a * X[:, 0] ** 2 - b * X[:, 2] ** 2
    under = exact - cm.max_std(X)
    assert (under > 1e-4).mean() > 0.9  # interpolation alone underestimates
    np.testing.assert_allclose(cm.max_std_high(X) - cm.max_std(X), CURVATURE_SAFETY * under, rtol=1e-9)
    # convex: interpolation already overestimates, nothing is added
    cm = costmap(lambda G: 1 + a * G[..., 0] ** 2)
    np.testing.assert_allclose(cm.max_std_high(X), cm.max_std(X), rtol=0)
    nodes = mesh().reshape(-1, 3)
    np.testing.assert_allclose(cm.max_std_high(nodes), 1 + a * nodes[:, 0] ** 2, rtol=1e-12)

    def bumps(P):  # a smooth field like a map's std: bumps a few cells wide
        return 2 + np.sin(P[..., 0] / 130) * np.cos(P[..., 1] / 170) + 0.5 * np.sin(P[..., 2] / 90)

    cm = costmap(bumps)
    X = random_points(20_000)
    under = bumps(X) - cm.max_std(X)
    assert under.max() > 0.05  # the plain interpolation is no bound
    assert (cm.max_std_high(X) >= bumps(X)).all()


def test_segment_cost_of_constant_fields_is_length_times_the_integrand():
    m = np.array([3.0, -1.0, 0.5])
    w = CostWeights(max_std_mps=2.0, risk=1.5, flow=0.7, cruise_mps=20.0)
    cm = costmap(
        lambda G: np.full(G.shape[:3], 1.0), mean=m, risk=w.risk, flow=w.flow, cruise_mps=w.cruise_mps
    )
    P0, P1 = np.array([[100.0, -200, 50], [500, 0, 10]]), np.array([[900.0, 300, 250], [500, 0, 290]])
    d = P1 - P0
    length = np.linalg.norm(d, axis=1)
    confidence = 1 / (1 + (1.0 / 2.0) ** 2)
    mismatch = np.linalg.norm(w.cruise_mps * d / length[:, None] - m, axis=1) / w.cruise_mps
    expected = length * (1 + w.risk * 1.0 / 2.0 + w.flow * confidence * mismatch)
    np.testing.assert_allclose(cm.segment_costs(P0, P1), expected, rtol=1e-12)
    # a batch equals its segments one by one, and a zero-length segment costs nothing
    for k in range(2):
        np.testing.assert_allclose(cm.segment_costs(P0[k], P1[k]), expected[k], rtol=1e-12)
    assert cm.segment_costs(P0[:1], P0[:1])[0] == 0.0


def test_linear_risk_integrates_exactly_and_costs_are_at_least_the_length():
    # risk = s / b, linear in x; no flow term: the trapezoid rule is exact
    cm = costmap(lambda G: 0.5 + 0.004 * G[..., 0], flow=0.0)
    a, b = np.array([50.0, 0, 100]), np.array([950.0, 120, 200])
    s_a, s_b = 0.5 + 0.004 * a[0], 0.5 + 0.004 * b[0]
    length = np.linalg.norm(b - a)
    expected = length * (1 + 0.5 * (s_a + s_b) / 2.0)
    np.testing.assert_allclose(cm.segment_costs(a, b), expected, rtol=1e-12)
    P0, P1 = random_points(200, 1), random_points(200, 2)
    assert (cm.segment_costs(P0, P1) >= np.linalg.norm(P1 - P0, axis=1) - 1e-9).all()


def test_one_segment_path_equals_the_batch_cost_and_tube_check():
    """What the planner's callbacks use, against the vectorised batch path, on segments
    inside, crossing and outside the tube (and of length 0)."""
    G = mesh()
    rng = np.random.default_rng(4)
    mean = np.stack([np.sin(G[..., 0] / 200), np.cos(G[..., 1] / 150), 0.01 * G[..., 2]], -1)
    std = 1.0 + np.abs(np.sin(G[..., 0] / 130))[..., None] * np.array([1.0, 0.5, 2.0])
    cm = CostMap(AXES, mean, std, CostWeights(max_std_mps=2.5, cruise_mps=3.0))
    P0 = random_points(300, seed=5)
    P1 = np.clip(P0 + rng.normal(0, 200, P0.shape), [0, -500, 0], [1000, 500, 300])
    P1[:5] = P0[:5]
    batch, tube = cm.segment_costs(P0, P1), cm.segments_in_tube(P0, P1)
    one = np.array([cm.segment(a, b) for a, b in zip(P0, P1, strict=True)])
    np.testing.assert_allclose(one[:, 0], batch, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(one[:, 1].astype(bool), tube)
    assert 0.1 < tube.mean() < 0.9 and (batch[:5] == 0).all()
    # sampled every half of the smallest grid step (50 m): every 25 m
    X, *_ = cm.samples(np.zeros((1, 3)), np.array([[1000.0, 0, 0]]))
    assert len(X) == 41


def test_exceedance_risk_is_the_gaussian_tail_probability():
    sigma, margin = 1.7, 2.5
    cm = costmap(lambda G: np.full(G.shape[:3], sigma), risk_kind="exceedance", margin_mps=margin, risk=2.0)
    p_component = 2 * norm.sf(margin / sigma)
    expected = 2.0 * (1 - (1 - p_component) ** 3)
    np.testing.assert_allclose(cm.fields(random_points(10))[:, 1], expected, rtol=1e-12)


def test_soft_tube_adds_a_penalty_above_the_bound_only():
    cm = costmap(lambda G: np.where(G[..., 0] < 500, 1.0, 4.0), tube="soft", tube_penalty=10.0, flow=0.0)
    inside, outside = cm.fields([[100.0, 0, 0]])[0, 1], cm.fields([[900.0, 0, 0]])[0, 1]
    assert inside == pytest.approx(1.0 / 2.0)
    assert outside == pytest.approx(4.0 / 2.0 + 10.0 * (4.0 / 2.0 - 1))


def test_path_metrics_on_a_straight_path():
    cm = costmap(lambda G: 1.0 + 0.002 * G[..., 0], flow=0.0, cruise_mps=25.0)
    P = np.array([[0.0, 0, 100], [400, 0, 100], [1000, 0, 100]])
    m = path_metrics(cm, P)
    assert m["length_m"] == pytest.approx(1000) and m["flight_time_s"] == pytest.approx(40)
    assert m["max_std_mps"] == pytest.approx(3.0) and m["mean_std_mps"] == pytest.approx(2.0)
    # s <= 2 m/s for x <= 500 m: half of the path
    assert m["in_tube_fraction"] == pytest.approx(0.5, abs=cm.sample_m / 1000)
    assert m["integrated_risk_m"] == pytest.approx(1000 * 2.0 / 2.0)
    assert m["cost_m"] == pytest.approx(1000 + m["integrated_risk_m"])


def test_box_hits_segments_exactly():
    box = Box((0.0, 0.0, 0.0), (10.0, 10.0, 10.0))
    P0 = np.array([[-5.0, 5, 5], [-5, 11, 5], [5, 5, 5], [-5, -5, -5], [10, 20, 5], [20, 5, 5]])
    P1 = np.array([[15.0, 5, 5], [15, 11, 5], [6, 6, 6], [-1, -1, -1], [10, 10, 5], [11, 5, 5]])
    # through, parallel above, inside, short of it, touching a face, stopping before it
    np.testing.assert_array_equal(box.hits(P0, P1), [True, False, True, False, True, False])
    with pytest.raises(ValueError, match="above lower"):
        Box((0.0, 0, 0), (1.0, 0, 1))


def test_problem_rejects_bad_input_with_a_reason():
    cm = costmap(lambda G: np.where(G[..., 0] < 500, 1.0, 4.0))
    ok = dict(costmap=cm, start=(100.0, 0, 100), goal=(200.0, 0, 100))
    with pytest.raises(ValueError, match="outside the tube"):
        PlanningProblem(**{**ok, "goal": (900.0, 0, 100)})
    with pytest.raises(ValueError, match="deadlocks"):
        PlanningProblem(**ok, planner="prmstar")
    with pytest.raises(ValueError, match="unknown planner"):
        PlanningProblem(**ok, planner="astar")
    with pytest.raises(ValueError, match="outside the planning box"):
        PlanningProblem(**ok, altitude_m=(150.0, 300.0))
    with pytest.raises(ValueError, match="no-fly"):
        PlanningProblem(**ok, no_fly=(Box((50.0, -10, 0), (150.0, 10, 300)),))
    with pytest.raises(ValueError, match="must be positive"):
        CostWeights(max_std_mps=0)
    with pytest.raises(ValueError, match="evenly spaced"):
        CostMap(
            (np.array([0.0, 1, 3]), *AXES[1:]), np.zeros((3, 11, 7, 3)), np.ones((3, 11, 7, 3)), cm.weights
        )


def test_voxels_without_data_count_as_far_outside_the_tube():
    G = mesh()
    std = np.full((*G.shape[:3], 3), 0.5)  # an empty tile's prior can be small
    known = G[..., 0] < 500
    cm = CostMap(AXES, np.ones_like(std), std, CostWeights(max_std_mps=2.0), known=known)
    np.testing.assert_allclose(cm.max_std([[100.0, 0, 0], [900.0, 0, 0]]), [0.5, 20.0])
    np.testing.assert_allclose(cm.fields([[900.0, 0, 0]])[0, 3:], 0.0)


def lanes(S=4):
    """A directional map: eastbound traffic at 20 m/s south of y = 0, westbound north of it,
    each well known in its lane (std 0.5); elsewhere every mode is the prior (std 8)."""
    G = mesh()
    sectors = Sectors(S)
    C = sectors.classes
    north = G[..., 1] > 0
    share = np.zeros((*G.shape[:3], C))
    east, west = S // 4, 3 * S // 4
    share[..., east] = np.where(north, 0.0, 1.0)
    share[..., west] = np.where(north, 1.0, 0.0)
    mean = np.zeros((*G.shape[:3], C, 3))
    mean[..., east, 0], mean[..., west, 0] = 20.0, -20.0
    std = np.full((*G.shape[:3], C, 3), 8.0)
    std[..., east, :] = np.where(north, 8.0, 0.5)[..., None]
    std[..., west, :] = np.where(north, 0.5, 8.0)[..., None]
    mix_mean = np.einsum("...c,...cd->...d", share, mean)
    mix_std = np.sqrt(np.einsum("...c,...cd->...d", share, std**2 + mean**2) - mix_mean**2)
    return mix_mean, mix_std, ModeGrids(share, mean, std, np.zeros_like(std), sectors)


def test_a_directional_map_costs_the_mode_flown_and_the_traffic_met():
    mix_mean, mix_std, modes = lanes()
    w = CostWeights(max_std_mps=2.0, cruise_mps=20.0, flow=0.5, conflict=1.0)
    cm = CostMap(AXES, mix_mean, mix_std, w, modes=modes)
    # flying east with the eastbound lane: its mode is known, no flow mismatch, nobody met
    P0, P1 = np.array([[100.0, -300, 100]]), np.array([[900.0, -300, 100]])
    risk_lane = 1.0 * 0.5 / 2.0
    np.testing.assert_allclose(cm.segment_costs(P0, P1), 800 * (1 + risk_lane), rtol=1e-12)
    # flying east in the westbound lane: the east mode is uncertain (its mean still 20 m/s:
    # no flow mismatch), the west traffic is met head on (closing at 40 m/s, confidence
    # 1 / (1 + 0.25^2))
    P0, P1 = np.array([[100.0, 300, 100]]), np.array([[900.0, 300, 100]])
    per_m = 1 + 8.0 / 2.0 + 1.0 / (1 + 0.25**2) * 2.0
    np.testing.assert_allclose(cm.segment_costs(P0, P1), 800 * per_m, rtol=1e-12)
    # the callbacks' one-segment path gives the same cost and tube answer
    for a, b in [((100.0, -300, 100), (900.0, -300, 100)), ((100.0, 300, 100), (900.0, 300, 100))]:
        cost, in_tube = cm.segment(np.array(a), np.array(b))
        np.testing.assert_allclose(cost, cm.segment_costs(np.array([a]), np.array([b]))[0], rtol=1e-12)
        assert in_tube == cm.segments_in_tube(np.array([a]), np.array([b]))[0]
    # the hard tube holds the mode flown: with the lane yes, against it no; a state is in the
    # tube when some mode is
    assert cm.segments_in_tube(np.array([[100.0, -300, 100]]), np.array([[900.0, -300, 100]]))[0]
    assert not cm.segments_in_tube(np.array([[900.0, -300, 100]]), np.array([[100.0, -300, 100]]))[0]
    assert (cm.max_std_high(random_points(100)) <= 0.5 + 1e-12).all()
    # exposure: the share of crossing or opposing traffic along the path
    m = path_metrics(cm, [[100.0, 300, 100], [900.0, 300, 100]])
    assert m["conflict_exposure"] == pytest.approx(1.0) and m["max_std_mps"] == pytest.approx(8.0)
    assert path_metrics(cm, [[900.0, 300, 100], [100.0, 300, 100]])["conflict_exposure"] == pytest.approx(0.0)


def test_the_mode_flown_is_the_maps_answer_for_its_heading():
    """The planner flies the library's mode of a heading (:func:`bdf.sectors.heading_mode`):
    one rule for routes, queries and assessment, its noise narrowed by the heading."""
    rng = np.random.default_rng(7)
    lower, upper = np.zeros(3), np.array([10.0, 8.0, 6.0])
    X = rng.uniform(lower, upper, (1500, 3))
    flown = np.radians(rng.uniform(0, 360, len(X)))  # headings spread: the pool turns with them
    V = np.stack([15 * np.sin(flown), 15 * np.cos(flown), 0.3 * np.sin(X[:, 0])], axis=1)
    V += 0.5 * rng.standard_normal(V.shape)
    sectors = Sectors(8)
    field = BayesianDynamicField(lower, upper, [2.0, 2.0, 1.5], [0.3, 0.2, 0.5], "auto", "auto", directions=8)
    field.fit(X, V)
    axes = tuple(np.linspace(lo, hi, n) for lo, hi, n in zip(lower, upper, (6, 5, 4), strict=True))
    modes = field.posterior_.predict_grid_modes(axes)
    mix_mean, mix_std = modes.answer(sectors)
    grid = ModeGrids(modes.share, modes.mean, modes.std, modes.heading_noise, sectors)
    cm = CostMap(axes, mix_mean, mix_std, CostWeights(max_std_mps=2.0, cruise_mps=15.0), modes=grid)
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    heading = rng.uniform(0, 360, len(nodes))
    h = np.radians(heading)
    direction = np.stack([np.sin(h), np.cos(h), 0 * h], axis=1)
    own = cm.flown(nodes, direction)[3]
    at_nodes = type(modes)(*(a.reshape(len(nodes), *a.shape[3:]) for a in modes))
    mean, std = at_nodes.answer(sectors, heading)
    np.testing.assert_allclose(own[:, 3:6], mean, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(own[:, 0], std.max(axis=1), rtol=1e-9)
    plain = type(modes)(*at_nodes[:-1], np.zeros_like(at_nodes.heading_noise)).answer(sectors, heading)[1]
    assert (std.max(axis=1) < 0.95 * plain.max(axis=1)).mean() > 0.2 and (std <= plain * (1 + 1e-12)).all()


def test_a_modes_heading_noise_lies_within_its_variance():
    """Heading noise is part of a mode's variance: the rounding of ``sqrt`` is let through,
    a negative value or one above the variance is refused."""
    mix_mean, mix_std, modes = lanes()
    w = CostWeights(max_std_mps=2.0, cruise_mps=20.0)
    variance = np.random.default_rng(1).uniform(0.1, 70.0, modes.std.shape)
    std = np.sqrt(variance)  # std**2 rounds to either side of variance
    CostMap(
        AXES, mix_mean, mix_std, w, modes=ModeGrids(modes.share, modes.mean, std, variance, modes.sectors)
    )
    for bad in (-1e-3 * variance, 1.001 * variance):
        with pytest.raises(ValueError, match="heading noise must lie between 0 and its variance"):
            CostMap(
                AXES, mix_mean, mix_std, w, modes=ModeGrids(modes.share, modes.mean, std, bad, modes.sectors)
            )


def test_a_directional_map_of_one_class_is_the_plain_map():
    mean = np.broadcast_to([3.0, -1.0, 0.5], (*mesh().shape[:3], 3))
    std = 1.0 + 0.001 * mesh()
    w = CostWeights(max_std_mps=2.0, conflict=1.0)
    plain = CostMap(AXES, mean, std, w)
    one = CostMap(
        AXES,
        mean,
        std,
        w,
        modes=ModeGrids(
            np.ones((*std.shape[:3], 1)),
            mean[..., None, :],
            std[..., None, :],
            0 * std[..., None, :],
            Sectors(1),
        ),
    )
    P = random_points(40, seed=3)
    np.testing.assert_allclose(
        one.segment_costs(P[:-1], P[1:]), plain.segment_costs(P[:-1], P[1:]), rtol=1e-12
    )
    np.testing.assert_array_equal(one.segments_in_tube(P[:-1], P[1:]), plain.segments_in_tube(P[:-1], P[1:]))
    with pytest.raises(ValueError, match="modes must have shapes"):
        CostMap(
            AXES,
            mean,
            std,
            w,
            modes=ModeGrids(
                np.ones((2, 2, 2, 1)),
                mean[..., None, :],
                std[..., None, :],
                0 * std[..., None, :],
                Sectors(1),
            ),
        )


def test_a_class_without_traffic_does_not_open_the_tube():
    """The slow class fitted as constant looks certain everywhere (std 1 mm/s) where it has
    no share: below MIN_SHARE it must not count, so the tube is the lanes' alone."""
    mix_mean, mix_std, modes = lanes()
    w = CostWeights(max_std_mps=2.0, cruise_mps=20.0, conflict=1.0)
    std = modes.std.copy()
    std[mesh()[..., 0] > 500, :-1, :] = 8.0  # east of x = 500 m the lanes are unknown
    modes = ModeGrids(modes.share, modes.mean, std.copy(), modes.heading_noise, modes.sectors)
    lanes_only = CostMap(AXES, mix_mean, mix_std, w, modes=modes)
    std[..., -1, :] = 0.001  # the slow class: certain, and no traffic in it
    share = modes.share.copy()
    share[..., -1] = 0.04
    share[..., :-1] *= 0.96
    empty_slow = CostMap(
        AXES,
        mix_mean,
        mix_std,
        w,
        modes=ModeGrids(share, modes.mean, std, modes.heading_noise, modes.sectors),
    )
    P = random_points(200, seed=5)
    states = empty_slow.segments_in_tube(P, P)  # a state (no length): in the tube if any flow is
    np.testing.assert_array_equal(states, lanes_only.segments_in_tube(P, P))
    assert 0 < states.sum() < len(P)
    np.testing.assert_allclose(empty_slow.fields(P)[:, :3], lanes_only.fields(P)[:, :3], rtol=1e-12)
    share[..., -1] = 1.0  # with all the traffic it is a flow like any other
    share[..., :-1] = 0.0
    slow = CostMap(
        AXES,
        mix_mean,
        mix_std,
        w,
        modes=ModeGrids(share, modes.mean, std, modes.heading_noise, modes.sectors),
    )
    assert (slow.fields(P)[:, 0] < 0.01).all()
