"""BayesianDynamicField against dense direct computations of the paper's equations."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import multivariate_normal

from bdf import BayesianDynamicField
from tests.bdf.conftest import GAMMA, LOWER, SPACING, UPPER, dense_features, flow


def dense_posterior(X, V, hinges, alpha, beta, noise_std=None):
    """Explicit Phi, explicit inverse, one posterior per component (the paper's way)."""
    P = dense_features(X, hinges, GAMMA, noise_std)
    out = []
    for c in range(3):
        sigma = np.linalg.inv(alpha[c] * np.eye(len(hinges)) + beta[c] * P.T @ P)
        out.append((sigma, beta[c] * sigma @ P.T @ V[:, c]))
    return out


def dense_predict(post, Xq, hinges, beta):
    Q = dense_features(Xq, hinges, GAMMA)
    mean = np.stack([Q @ mu for _, mu in post], 1)
    epistemic = np.stack([np.einsum("nm,mk,nk->n", Q, s, Q) for s, _ in post], 1)
    return mean, epistemic, epistemic + 1 / np.asarray(beta)


def assert_close(actual, desired, rtol, what):
    """Relative error per value, each against at least a millionth of the largest (a mean
    near 0 carries the rounding of the values it sums, not its own size)."""
    floor = 1e-6 * np.abs(desired).max() + 1e-300
    err = np.max(np.abs(actual - desired) / np.maximum(np.abs(desired), floor))
    assert err <= rtol, f"{what}: max relative error {err:.3g} > {rtol}"


@pytest.mark.parametrize("beta", [10.0, [10.0, 4.0, 25.0]])
def test_matches_dense_computation(data, beta):
    X, V = data
    field = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=0.5, beta=beta).fit(X, V)
    alpha_v, beta_v = np.full(3, 0.5), np.broadcast_to(beta, (3,))
    post = dense_posterior(X, V, field.hinges, alpha_v, beta_v)
    Xq = np.random.default_rng(1).uniform(LOWER - 2, UPPER + 2, (200, 3))
    mean_ref, epi_ref, var_ref = dense_predict(post, Xq, field.hinges, beta_v)

    mean, std = field.predict(Xq, return_std=True)
    _, epi_std = field.predict(Xq, return_std=True, include_noise=False)
    assert_close(mean, mean_ref, 1e-8, "mean")
    assert_close(std**2, var_ref, 1e-8, "predictive variance")
    assert_close(epi_std**2, epi_ref, 1e-8, "epistemic variance")
    assert_close(field.weights_, np.stack([mu for _, mu in post], 1), 1e-8, "posterior mean weights")


def test_hinges_cover_box_inclusive():
    field = BayesianDynamicField([0, 0, 0], [10, 4, 3], [2, 2, 1.5], 1.0)
    h = field.hinges
    assert h.shape == (6 * 3 * 3, 3)
    np.testing.assert_array_equal(h.max(0), [10, 4, 3])
    np.testing.assert_array_equal(h[:3], [[0, 0, 0], [0, 0, 1.5], [0, 0, 3]])


def test_log_evidence_equals_gaussian_marginal_likelihood(data):
    X, V = data
    field = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=0.5, beta=[10.0, 4.0, 25.0]).fit(X, V)
    P = dense_features(X, field.hinges, GAMMA)
    for c, b in enumerate([10.0, 4.0, 25.0]):
        cov = P @ P.T / 0.5 + np.eye(len(X)) / b
        ref = multivariate_normal(np.zeros(len(X)), cov).logpdf(V[:, c])
        assert field.log_evidence_[c] == pytest.approx(ref, rel=1e-9)


@pytest.mark.parametrize(("alpha", "beta"), [("auto", "auto"), ("auto", 30.0), (0.5, "auto")])
def test_auto_hyperparameters_maximise_the_evidence(data, alpha, beta):
    """Moving off the fitted values, along each direction being fitted, lowers the evidence.

    alpha/beta is shared by the components, so along it only the sum is maximal; each
    component's beta (at a fixed ratio, or with alpha fixed) is maximal on its own.
    """
    X, V = data
    fitted = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=alpha, beta=beta).fit(X, V)
    best = fitted.log_evidence_

    def evidence(a, b):
        return BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=a, beta=b).fit(X, V).log_evidence_

    for f in (0.8, 1.25):
        if alpha == "auto":  # the shared ratio
            assert evidence(fitted.alpha_ * f, fitted.beta_).sum() < best.sum()
        if beta == "auto":  # each component's noise precision
            a = fitted.alpha_ * f if alpha == "auto" else fitted.alpha_
            assert np.all(evidence(a, fitted.beta_ * f) < best)


def test_auto_hyperparameters_are_calibrated():
    rng = np.random.default_rng(3)
    X = rng.uniform(LOWER, UPPER, (3000, 3))
    V = flow(X) + 0.2 * rng.standard_normal(X.shape)
    train, test = slice(0, 2000), slice(2000, None)
    field = BayesianDynamicField(LOWER, UPPER, SPACING / 2, GAMMA * 4, alpha="auto", beta="auto")
    mean, std = field.fit(X[train], V[train]).predict(X[test], return_std=True)
    inside = np.mean(np.abs(V[test] - mean) <= 1.96 * std)
    assert 0.93 <= inside <= 0.97
    np.testing.assert_allclose(1 / np.sqrt(field.beta_), 0.2, rtol=0.1)


@settings(max_examples=25, deadline=None, derandomize=True)  # seeded: the same examples every run
@given(
    cuts=st.lists(st.integers(1, 299), min_size=1, max_size=5, unique=True),
    seed=st.integers(0, 2**16),
    auto=st.booleans(),
)
def test_partial_fit_over_any_split_and_order_equals_fit(cuts, seed, auto):
    rng = np.random.default_rng(seed)
    X = rng.uniform(LOWER - 1, UPPER + 1, (300, 3))
    V = flow(X) + 0.1 * rng.standard_normal(X.shape)
    hyper = {"alpha": "auto", "beta": "auto"} if auto else {"alpha": 0.5, "beta": 10.0}
    batch = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **hyper).fit(X, V)
    chunks = np.split(rng.permutation(300), sorted(cuts))
    sequential = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **hyper)
    for i in rng.permutation(len(chunks)):
        sequential.partial_fit(X[chunks[i]], V[chunks[i]])
    Xq = rng.uniform(LOWER, UPPER, (50, 3))
    m1, s1 = batch.predict(Xq, return_std=True)
    m2, s2 = sequential.predict(Xq, return_std=True)
    assert_close(m2, m1, 1e-9, "mean")
    assert_close(s2, s1, 1e-9, "std")
    assert_close(sequential.evidence_.classes[0].proj, batch.evidence_.classes[0].proj, 1e-9, "Phi^T V")


def test_far_from_data_the_prior_is_returned(data):
    X, V = data
    field = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=0.5, beta=10.0).fit(X, V)
    far = np.array([[100.0, 100.0, 100.0]])
    mean, std = field.predict(far, return_std=True)
    np.testing.assert_array_equal(mean, 0.0)
    np.testing.assert_allclose(std, np.sqrt(1 / 10.0))
    # inside the grid but away from all data: prior variance 1/beta + sum_m phi_m^2 / alpha
    lonely = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=0.5, beta=10.0).fit(
        np.array([[100.0, 100.0, 100.0]]), np.ones((1, 3))
    )
    x = np.array([[5.0, 4.0, 3.0]])
    prior_var = 1 / 10.0 + np.sum(dense_features(x, lonely.hinges, GAMMA) ** 2) / 0.5
    np.testing.assert_allclose(lonely.predict(x, return_std=True)[1], np.sqrt(prior_var), rtol=1e-12)


def test_noisy_inputs_use_the_expected_kernel(data):
    X, V = data
    rng = np.random.default_rng(2)
    noise = np.abs(rng.normal(0, 0.4, X.shape))
    noise[::3] = 0.0  # a mix of exact and noisy points
    field = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=0.5, beta=10.0)
    field.fit(X, V, input_noise_std=noise)
    post = dense_posterior(X, V, field.hinges, np.full(3, 0.5), np.full(3, 10.0), noise_std=noise)
    Xq = rng.uniform(LOWER, UPPER, (100, 3))
    mean_ref, _, var_ref = dense_predict(post, Xq, field.hinges, np.full(3, 10.0))
    mean, std = field.predict(Xq, return_std=True)
    assert_close(mean, mean_ref, 1e-8, "mean with noisy inputs")
    assert_close(std**2, var_ref, 1e-8, "variance with noisy inputs")

    zero = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=0.5, beta=10.0)
    zero.fit(X, V, input_noise_std=0.0)
    plain = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=0.5, beta=10.0).fit(X, V)
    np.testing.assert_array_equal(zero.predict(Xq), plain.predict(Xq))


def test_expected_kernel_matches_monte_carlo():
    rng = np.random.default_rng(4)
    x, h, nu = np.array([[1.0, 2.0, 0.5]]), np.array([[1.5, 1.0, 0.0]]), np.array([[0.3, 0.6, 0.2]])
    samples = x + nu * rng.standard_normal((400_000, 3))
    mc = dense_features(samples, h, GAMMA).mean()
    np.testing.assert_allclose(dense_features(x, h, GAMMA, nu)[0, 0], mc, rtol=5e-3)


def test_forgetting_removes_old_flow_after_many_half_lives():
    rng = np.random.default_rng(5)
    X = rng.uniform(LOWER, UPPER, (400, 3))
    old, new = flow(X), -flow(X)
    kwargs = {"alpha": 0.5, "beta": 10.0, "half_life": 10.0}
    field = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **kwargs).fit(X, old, time=0.0)
    field.partial_fit(X, new, time=1000.0)  # 100 half-lives
    fresh = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **kwargs).fit(X, new)
    assert_close(field.predict(X), fresh.predict(X), 1e-9, "mean after forgetting")
    # one half-life weighs the old evidence by exactly one half
    half = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **kwargs).fit(X, old, time=0.0)
    half.partial_fit(X, new, time=10.0)
    expected = 0.5 * fresh.evidence_.classes[0].proj * -1 + fresh.evidence_.classes[0].proj
    assert_close(half.evidence_.classes[0].proj, expected, 1e-12, "Phi^T V after one half-life")
    with pytest.raises(ValueError, match="before the previous update"):
        half.partial_fit(X, new, time=5.0)


def test_save_load_round_trip(tmp_path, data):
    X, V = data
    field = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha="auto", beta=10.0).fit(X, V)
    field.partial_fit(X[:10], V[:10], input_noise_std=0.3)
    path = tmp_path / "field.bdf"
    field.save(path)
    loaded = BayesianDynamicField.load(path)
    Xq = X[:20] + 0.1
    np.testing.assert_array_equal(loaded.predict(Xq, return_std=True), field.predict(Xq, return_std=True))
    assert loaded.get_params() == {k: _as_list(v) for k, v in field.get_params().items()}
    assert loaded.alpha == "auto" and loaded.time_ == field.time_
    # one changed value is seen; an unknown format version fails loudly
    with np.load(path) as npz:
        arrays = dict(npz)
    arrays["evidence_0_proj"] = arrays["evidence_0_proj"] * 1.001
    np.savez(tmp_path / "changed.npz", **arrays)
    changed = BayesianDynamicField.load(tmp_path / "changed.npz")
    assert not np.allclose(changed.predict(Xq), field.predict(Xq), rtol=1e-6, atol=0)
    arrays["format_version"] = np.array(99)
    np.savez(tmp_path / "future.npz", **arrays)
    with pytest.raises(ValueError, match="format version 99"):
        BayesianDynamicField.load(tmp_path / "future.npz")


def _as_list(value):
    return value if isinstance(value, str | type(None)) else np.asarray(value, float).tolist()


BAD_INPUTS = [
    ({"X": np.full((3, 3), np.nan)}, "NaN or infinite values in rows \\[0, 1, 2\\]"),
    ({"X": np.zeros((3, 2))}, "X must have shape \\(N, 3\\)"),
    ({"X": np.zeros((0, 3)), "V": np.zeros((0, 3))}, "X is empty"),
    ({"V": np.zeros((4, 3))}, "X has 3 rows but V has 4"),
    ({"V": np.array([[0, 0, 0], [0, np.inf, 0], [0, 0, 0]])}, "V has NaN or infinite values in rows \\[1\\]"),
    ({"spacing": 0.0}, "spacing must be positive"),
    ({"spacing": [1.0, -1.0, 1.0]}, "spacing must be positive"),
    ({"gamma": [1.0, 0.0, 1.0]}, "gamma must be positive"),
    ({"gamma": [1.0, 1.0]}, "gamma must be a number or 3 numbers"),
    ({"alpha": "best"}, "alpha must be a positive number, 3 numbers or 'auto'"),
    ({"beta": -1.0}, "beta must be positive"),
    ({"upper": [0, 8, 6]}, "must exceed lower"),
    ({"spacing": 0.01}, "more than 250000; increase spacing"),
    ({"noise": -1.0}, "input_noise_std must be finite and >= 0"),
]


@pytest.mark.parametrize(("change", "message"), BAD_INPUTS)
def test_bad_input_is_a_clear_value_error(change, message):
    args = {
        "X": np.ones((3, 3)),
        "V": np.ones((3, 3)),
        "spacing": SPACING,
        "gamma": GAMMA,
        "alpha": 1.0,
        "beta": 1.0,
        "upper": UPPER,
        "noise": None,
    }
    args.update(change)
    field = BayesianDynamicField(
        LOWER, args["upper"], args["spacing"], args["gamma"], alpha=args["alpha"], beta=args["beta"]
    )
    with pytest.raises(ValueError, match=message):
        field.fit(args["X"], args["V"], input_noise_std=args["noise"])


def test_predict_before_fit_is_a_value_error():
    with pytest.raises(ValueError, match="not been fitted"):
        BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA).predict(np.zeros((1, 3)))


def test_sample_weight_equals_repeating_points(data):
    X, V = data
    weights = np.tile([0.0, 1.0, 2.0], 100)
    weighted = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha="auto", beta="auto")
    weighted.fit(X, V, sample_weight=weights)
    repeat = np.repeat(np.arange(len(X)), weights.astype(int))
    repeated = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha="auto", beta="auto").fit(
        X[repeat], V[repeat]
    )
    Xq = X[:40] + 0.3
    assert_close(
        weighted.predict(Xq, return_std=True)[1], repeated.predict(Xq, return_std=True)[1], 1e-9, "std"
    )
    assert_close(weighted.predict(Xq), repeated.predict(Xq), 1e-9, "mean")
    assert_close(weighted.beta_, repeated.beta_, 1e-9, "fitted beta")
    with pytest.raises(ValueError, match="sample_weight must be finite and >= 0"):
        weighted.fit(X, V, sample_weight=-weights)
