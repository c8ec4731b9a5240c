from unittest import mock

import numpy as np
import pytest

from bdf import BayesianDynamicField, metrics
from bdf.crossval import cross_validate
from tests.bdf.conftest import LOWER, UPPER, flow


def test_cross_validation_prefers_the_bandwidth_that_resolves_the_flow():
    rng = np.random.default_rng(0)
    X = rng.uniform(LOWER, UPPER, (1500, 3))
    V = flow(X) + 0.05 * rng.standard_normal(X.shape)
    candidates = [(1.0, 1.0), (4.0, 0.02)]  # fine enough vs far too smooth for sin(x)
    best, table = cross_validate(X, V, LOWER, UPPER, candidates, n_splits=3)
    assert best["spacing"] == [1.0, 1.0, 1.0]
    assert [row["hinges"] for row in table] == [11 * 9 * 7, 3 * 3 * 2]
    assert table[0]["rmse"] < 0.5 * table[1]["rmse"]
    best_rmse, _ = cross_validate(
        X, V, LOWER, UPPER, candidates, n_splits=3, score="rmse", groups=np.arange(len(X)) // 100
    )
    assert best_rmse["spacing"] == [1.0, 1.0, 1.0]
    # unit weights change nothing; doubling every weight is seen (the evidence counts N twice)
    _, unit = cross_validate(X, V, LOWER, UPPER, candidates, n_splits=3, sample_weight=np.ones(len(X)))
    assert unit == table
    _, double = cross_validate(X, V, LOWER, UPPER, candidates, n_splits=3, sample_weight=np.full(len(X), 2.0))
    assert double[0]["msll"] != table[0]["msll"]


def test_cross_validation_scores_local_noise():
    """Half the box scatters 20x more than the other: local noise wins the CV MSLL, and
    its score is that of fields fitted on the folds by hand."""
    rng = np.random.default_rng(1)
    X = rng.uniform(LOWER, UPPER, (3000, 3))
    V = flow(X) + np.where(X[:, :1] < 5.0, 0.05, 1.0) * rng.standard_normal(X.shape)
    candidates = [(2.0, 0.3)]
    _, (plain,) = cross_validate(X, V, LOWER, UPPER, candidates, n_splits=2)
    _, (local,) = cross_validate(X, V, LOWER, UPPER, candidates, n_splits=2, noise_spacing=1.0)
    assert local["msll"] < plain["msll"] - 0.2
    assert local["rmse"] == pytest.approx(plain["rmse"], rel=1e-9)  # the mean is unchanged
    fold = np.random.default_rng(0).permutation(len(X)) % 2
    by_hand = []
    for k in range(2):
        test = fold == k
        field = BayesianDynamicField(LOWER, UPPER, 2.0, 0.3, "auto", "auto", noise_spacing=1.0)
        mean, std = field.fit(X[~test], V[~test]).predict(X[test], return_std=True)
        by_hand.append(metrics.msll(V[test], mean, std, V[~test].mean(0), V[~test].std(0)))
    assert local["msll"] == pytest.approx(np.mean(by_hand), rel=1e-9)


def test_cross_validation_rejects_bad_arguments():
    X = np.zeros((10, 3))
    with pytest.raises(ValueError, match="score must be"):
        cross_validate(X, X, LOWER, UPPER, [(1.0, 1.0)], score="r2")
    with pytest.raises(ValueError, match="2 groups cannot fill 3 folds"):
        cross_validate(X, X, LOWER, UPPER, [(1.0, 1.0)], n_splits=3, groups=np.arange(10) % 2)
    with pytest.raises(ValueError, match="noise_prior must be a positive number"):
        cross_validate(X, X, LOWER, UPPER, [(1.0, 1.0)], noise_spacing=1.0, noise_prior=-1)
    with pytest.raises(ValueError, match="directions must be"):
        cross_validate(X, X, LOWER, UPPER, [(1.0, 1.0)], directions="many")


def test_auto_beta_is_bounded_for_a_constant_component():
    """Vertical speed exactly 0 everywhere: the noise std stops at 1 mm/s, not 1e-150."""
    from bdf.hyperparameters import MAX_AUTO_BETA

    rng = np.random.default_rng(0)
    X = rng.uniform(0, 100, (400, 3))
    V = np.stack([np.sin(X[:, 0] / 20), np.cos(X[:, 1] / 20), np.zeros(len(X))], axis=1)
    f = BayesianDynamicField([0, 0, 0], [100, 100, 100], 20, 1 / 400, alpha="auto", beta="auto").fit(X, V)
    assert f.beta_[2] == MAX_AUTO_BETA and f.beta_[0] < MAX_AUTO_BETA
    _, std = f.predict(X[:5], return_std=True)
    assert np.all(std[:, 2] >= MAX_AUTO_BETA**-0.5) and np.all(std[:, 2] < 1e-2)


def test_a_fixed_alpha_stays_fixed_where_auto_beta_meets_its_bound():
    """beta = alpha / lam with alpha fixed: the search keeps lam above alpha / MAX_AUTO_BETA,
    so the bound on beta never moves alpha off the value given (it used to: 0.64 for 1)."""
    from bdf.hyperparameters import MAX_AUTO_BETA

    X = np.zeros((2, 3))
    V = np.array([[0.0, -1.0, 0.0]] * 2)
    f = BayesianDynamicField([0, 0, 0], [100, 100, 100], 20, 1 / 400, alpha=1.0, beta="auto")
    f.fit(X, V, sample_weight=[1e-6, 1000.0])
    np.testing.assert_array_equal(f.alpha_, 1.0)
    np.testing.assert_allclose(f.beta_, MAX_AUTO_BETA, rtol=1e-12)
    refit = BayesianDynamicField([0, 0, 0], [100, 100, 100], 20, 1 / 400, alpha=1.0, beta=f.beta_)
    np.testing.assert_allclose(
        refit.fit(X, V, sample_weight=[1e-6, 1000.0]).predict(X), f.predict(X), rtol=1e-9
    )


@pytest.mark.parametrize(("alpha", "beta"), [("auto", "auto"), ("auto", 30.0), (0.5, "auto")])
def test_search_derivatives_equal_finite_differences_of_the_evidence(alpha, beta):
    """The search's slope and curvature in ln(alpha / beta), with exact traces (the probes
    sqrt(M) times the unit vectors), against central differences of the exact evidence;
    and the 64 random probes stay within 3 % of the slope's scale."""
    from bdf import hyperparameters
    from bdf.sparse import stencil_on

    rng = np.random.default_rng(3)
    X = rng.uniform(LOWER, UPPER, (600, 3))
    V = flow(X) + 0.1 * rng.standard_normal(X.shape)
    V[:, 2] = 0.3 * V[:, 2]  # the components' noise differs: their betas differ
    field = BayesianDynamicField(LOWER, UPPER, 2.0, 0.25, alpha=0.5, beta=10.0).fit(X, V)
    ev = field.evidence_.total()
    stencil = stencil_on(field.posterior_.grid, field.posterior_.kernel)
    band = ev.gram_band(stencil)
    M = stencil.size
    exact = np.sqrt(M) * np.eye(M)
    comps = [0] if (beta == "auto" and alpha != "auto") else [0, 1, 2]
    tied, profiled = alpha != "auto", np.full(3, alpha == "auto" and beta == "auto")

    def at(x, probes=exact):
        sol = hyperparameters.solve(stencil, band, ev.proj, ev.v_sq, np.exp(x))
        a, b = hyperparameters._hyper_for(sol, alpha, beta, ev.count)
        cost = -float(np.sum(hyperparameters.log_evidence(sol, a, b, ev.count)[comps]))
        return cost, hyperparameters._derivatives(sol, a, b, ev.count, comps, tied, profiled, probes)

    x, h = np.log(0.05), 1e-4
    _, (slope, curvature, _) = at(x)
    (up, (up_slope, _, _)), (down, (down_slope, _, _)) = at(x + h), at(x - h)
    assert slope == pytest.approx((up - down) / (2 * h), rel=1e-5)
    assert curvature == pytest.approx((up_slope - down_slope) / (2 * h), rel=1e-5)
    _, (estimate, _, _) = at(x, hyperparameters._probes(M))
    assert abs(estimate - slope) < 0.03 * M


def test_cross_validation_of_directional_maps_scores_the_mixture():
    """Two opposing streams over the same box: one field averages them to nothing, four
    heading sectors keep both; the CV's MSLL sees it."""
    rng = np.random.default_rng(4)
    X = rng.uniform(LOWER, UPPER, (1200, 3))
    sign = np.where(np.arange(len(X)) % 2 == 0, 1.0, -1.0)
    V = sign[:, None] * np.array([8.0, 0.0, 0.0]) + 0.3 * rng.standard_normal(X.shape)
    groups = np.arange(len(X)) // 40  # each "flight" mixes both streams
    rows = {
        S: cross_validate(X, V, LOWER, UPPER, [(2.0, 0.25)], n_splits=3, groups=groups, directions=S)[0]
        for S in (1, 4)
    }
    assert rows[4]["directions"] == 4 and rows[1]["directions"] == 1
    assert rows[4]["msll"] < rows[1]["msll"] - 0.3


def test_auto_directions_resolve_crossing_flows_at_twelve_headings():
    """Straight flights at 12 evenly spread headings (every 30 degrees) cross one box: 8
    sectors (45 degrees) merge neighbouring flows into one mode; "auto" picks a resolution
    of at least 12 by the flights' held-out mixture MSLL, and the mode of a flown heading
    is then a third closer than with 8."""
    rng = np.random.default_rng(12)
    flights, points = [], []
    for k in range(144):
        heading = np.radians(30.0 * (k % 12))
        direction = np.array([np.sin(heading), np.cos(heading), 0.0])
        start = rng.uniform(LOWER, UPPER) - 8.0 * direction
        X = start + np.linspace(0.0, 16.0, 40)[:, None] * direction
        inside = np.all((X >= LOWER) & (X <= UPPER), axis=1)
        points.append((X[inside], np.broadcast_to(10.0 * direction, X[inside].shape)))
        flights.append(np.full(inside.sum(), k))
    X = np.concatenate([p[0] for p in points])
    V = np.concatenate([p[1] for p in points]) + 0.3 * rng.standard_normal((len(X), 3))
    groups = np.concatenate(flights)
    best, table = cross_validate(
        X, V, LOWER, UPPER, [(2.0, 0.25)], n_splits=3, groups=groups, directions="auto"
    )
    assert [row["directions"] for row in table] == [8, 16, 24, 32]
    eight = table[0]
    assert best["directions"] >= 12, table
    assert best["cond_rmse"] <= eight["cond_rmse"] * 2 / 3, table


def test_the_search_stays_above_the_truncation_floor_of_the_gram_matrix():
    """Below ``FLOOR_PER_CUTOFF x cutoff x mean(diag G)`` the smallest eigenvalues of ``G``
    are truncation noise and so is the evidence: a search started far below (as a mode's
    starts at its map's ratio) never factors there, and ends inside the bounds."""
    from bdf import hyperparameters

    rng = np.random.default_rng(0)
    X = rng.uniform(0, 100, (400, 3))
    V = np.stack([np.sin(X[:, 0] / 20), np.cos(X[:, 1] / 20), X[:, 2] / 100], axis=1)
    f = BayesianDynamicField([0, 0, 0], [100, 100, 100], 20, 1 / 400, cutoff=1e-12).fit(X, V)
    evidence, stencil = f.evidence_.total(), f.posterior_.stencil
    band = evidence.gram_band(stencil)
    floor = hyperparameters.FLOOR_PER_CUTOFF * 1e-12 * np.mean(band[0])
    with mock.patch.object(hyperparameters, "solve", wraps=hyperparameters.solve) as solve:
        fit = hyperparameters.fit_evidence(
            stencil, band, evidence.proj, evidence.v_sq, evidence.count, "auto", "auto", start=1e-20
        )
        seen = [call.args[4] for call in solve.call_args_list]
    assert min(seen) >= floor * (1 - 1e-12)
    assert np.all(fit.alpha / fit.beta >= floor * (1 - 1e-12))
    # a slope that always points down: the search stops at the floor, never below
    xs = []

    def falling(x):
        xs.append(x)
        return 1.0, 1.0, x - 10.0

    hyperparameters._search(falling, -5.0, (-8.0, 3.0))
    assert min(xs) == -8.0 and all(-8.0 <= x <= 3.0 for x in xs)


@pytest.mark.parametrize("directions", [1, 8])
def test_a_search_that_need_not_settle_stops_within_a_nat_and_settles_from_where_it_pointed(directions):
    """After a small addition of data, the search from the previous optimum with
    ``settle=False`` stops at its first point (the map with one class; a class with few
    data may take a step more), whose evidence is within a nat of the
    optimum's; its ``next_start`` is a hundred times closer to the optimum, and a settled
    search from there finds the optimum of one fit of all the data (to the search's
    tolerance) in fewer factorisations than from the previous optimum."""
    from bdf.hyperparameters import EVIDENCE_TOLERANCE, LOG_TOLERANCE

    rng = np.random.default_rng(11)
    X = rng.uniform(LOWER, UPPER, (3000, 3))
    V = flow(X) + 0.3 * rng.standard_normal(X.shape)
    make = dict(alpha="auto", beta="auto", directions=directions)
    before = BayesianDynamicField(LOWER, UPPER, 2.0, 0.25, **make).fit(X[:2900], V[:2900])
    start = before.alpha_ / before.beta_
    evidence = BayesianDynamicField(LOWER, UPPER, 2.0, 0.25, **make).fit(X, V).evidence_
    fresh = BayesianDynamicField(LOWER, UPPER, 2.0, 0.25, **make)
    quick = fresh.set_evidence(evidence, start=start, settle=False).posterior_
    searches = 1 if directions == 1 else 1 + directions  # the map with one class, and each class
    assert not quick.settled and 0 < quick.evidence_gap < EVIDENCE_TOLERANCE * searches
    np.testing.assert_allclose(quick.alpha[0] / quick.beta[0], np.reshape(start, (-1, 3))[0], rtol=1e-12)

    settled = fresh.set_evidence(evidence, start=quick.next_start).posterior_
    warm = fresh.set_evidence(evidence, start=start).posterior_
    single = BayesianDynamicField(LOWER, UPPER, 2.0, 0.25, **make).fit(X, V).posterior_
    assert settled.settled and settled.evidence_gap == 0
    for got in (settled, warm):
        np.testing.assert_allclose(
            np.log(got.alpha / got.beta), np.log(single.alpha / single.beta), atol=10 * LOG_TOLERANCE
        )
    assert settled.factorisations < warm.factorisations
    assert quick.factorisations < warm.factorisations and (directions > 1 or quick.factorisations == 1)
    lacked = float(np.sum(settled.log_evidence) - np.sum(quick.log_evidence))
    assert abs(lacked) < EVIDENCE_TOLERANCE
    optimum = np.log(settled.alpha / settled.beta)
    far, near = np.abs(np.log(start) - optimum), np.abs(np.log(quick.next_start) - optimum)
    assert np.all(near <= 0.01 * far)


def test_a_search_that_ends_at_the_floor_factors_no_ratio_twice():
    """Noise-free data put the optimum below the truncation floor: the searches from the
    previous optimum and from the anchor end there, and the answer is the anchor's loose
    search, read from the points already factored (no ratio is factored twice), at the
    best evidence among them."""
    from bdf import hyperparameters

    rng = np.random.default_rng(2)
    X = rng.uniform(LOWER, UPPER, (2000, 3))
    field = BayesianDynamicField(LOWER, UPPER, 2.0, 0.25, cutoff=1e-6).fit(X, flow(X))
    evidence, stencil = field.evidence_.total(), field.posterior_.stencil
    band = evidence.gram_band(stencil)
    with mock.patch.object(hyperparameters, "solve", wraps=hyperparameters.solve) as solve:
        fit = hyperparameters.fit_evidence(
            stencil, band, evidence.proj, evidence.v_sq, evidence.count, "auto", "auto", start=1.0
        )
        seen = [call.args[4] for call in solve.call_args_list]
    floor = hyperparameters.FLOOR_PER_CUTOFF * 1e-6 * np.mean(band[0])
    assert fit.settled and fit.alpha[0] / fit.beta[0] < floor * np.exp(hyperparameters.NEAR_FLOOR)
    assert len(set(seen)) == len(seen) == fit.factorisations

    def evidence_at(lam):
        sol = hyperparameters.solve(stencil, band, evidence.proj, evidence.v_sq, lam)
        alpha, beta = hyperparameters._hyper_for(sol, "auto", "auto", evidence.count)
        return hyperparameters.log_evidence(sol, alpha, beta, evidence.count).sum()

    values = {lam: evidence_at(lam) for lam in seen}
    assert max(values, key=values.get) == pytest.approx(fit.alpha[0] / fit.beta[0], rel=1e-12)


def test_an_abandoned_computation_stops_at_its_next_factorisation():
    """Inside ``abandon_when(stop)`` a posterior's search raises ``Abandoned`` at the first
    factorisation after ``stop()`` turns true (the factorisations before it ran), and so
    does its variance; outside the block, the same fit is whole."""
    from bdf.hyperparameters import Abandoned, abandon_when

    rng = np.random.default_rng(12)
    X = rng.uniform(LOWER, UPPER, (1500, 3))
    V = flow(X) + 0.3 * rng.standard_normal(X.shape)
    field = BayesianDynamicField(LOWER, UPPER, 2.0, 0.25, alpha="auto", beta="auto").fit(X, V)
    whole = field.posterior_
    assert whole.factorisations >= 3
    asked = []

    def stop_after(n):
        def stop():
            asked.append(n)
            return asked.count(n) > n

        return stop

    with abandon_when(stop_after(2)), pytest.raises(Abandoned):
        field.set_evidence(field.evidence_).posterior_.compact()
    assert asked.count(2) == 3  # two factorisations ran, the third was given up
    searched = field.set_evidence(field.evidence_).posterior_
    with abandon_when(lambda: True), pytest.raises(Abandoned):
        searched.variance_table()
    np.testing.assert_allclose(searched.weights, whole.weights, rtol=0, atol=0)
    assert field.set_evidence(field.evidence_).posterior_.compact().factorisations == whole.factorisations
