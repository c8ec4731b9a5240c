"""Local noise (bdf.noise) against a dense direct computation, and its behaviour in a field."""

import numpy as np
import pytest

from bdf import BayesianDynamicField, features
from bdf.kernel import NOISE_CUTOFF
from bdf.sectors import Sectors
from bdf.statistics import SectorEvidence
from tests.bdf.conftest import GAMMA, LOWER, SPACING, UPPER
from tests.bdf.test_field import assert_close

NOISE_SPACING = np.array([1.0, 1.0, 0.5])
PRIOR = 0.3


def dense_noise_variance(X, V, weight, Xq, mean, beta):
    """sigma^2 at Xq from the explicit smoother: lattice points listed, every term kept,
    residuals summed point by point."""
    axes = [np.arange(LOWER[d], UPPER[d] + 1e-9, NOISE_SPACING[d]) for d in range(3)]
    G = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)

    def basis(P):
        return np.exp(-(((P[:, None, :] - G[None]) / NOISE_SPACING) ** 2).sum(-1))

    k = basis(Xq) @ basis(X).T  # (nq, n)
    peak = (np.pi / 2) ** 1.5
    a0 = k @ weight
    squares = np.stack([(k * weight * (V[None, :, c] - mean[:, c, None]) ** 2).sum(1) for c in range(3)], 1)
    return (squares / peak + PRIOR / beta) / (a0[:, None] / peak + PRIOR)


def test_local_noise_matches_dense_computation(data):
    X, V = data
    weight = np.random.default_rng(2).uniform(0.2, 2.0, len(X))
    field = BayesianDynamicField(
        LOWER,
        UPPER,
        SPACING,
        GAMMA,
        alpha=0.5,
        beta=[10.0, 4.0, 25.0],
        noise_spacing=NOISE_SPACING,
        noise_prior=PRIOR,
    ).fit(X, V, sample_weight=weight)
    Xq = np.random.default_rng(1).uniform(LOWER - 2, UPPER + 2, (100, 3))
    mean, std = field.predict(Xq, return_std=True)
    _, epistemic = field.predict(Xq, return_std=True, include_noise=False)
    expected = dense_noise_variance(X, V, weight, Xq, mean, field.beta_)
    # the moments drop per-axis factors below NOISE_CUTOFF (the dense sum keeps them)
    assert_close(std**2 - epistemic**2, expected, 20 * NOISE_CUTOFF, "local noise variance")
    # the mean and the epistemic part are those of the global-noise field
    plain = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, alpha=0.5, beta=[10.0, 4.0, 25.0])
    plain.fit(X, V, sample_weight=weight)
    m0, e0 = plain.predict(Xq, return_std=True, include_noise=False)
    np.testing.assert_array_equal(mean, m0)
    np.testing.assert_array_equal(epistemic, e0)


def test_local_noise_finds_where_the_flow_scatters():
    """Left half scatters by 0.05, right half by 1.0: the global noise is wrong on both."""
    rng = np.random.default_rng(0)
    X = rng.uniform(LOWER, UPPER, (20000, 3))
    scatter = np.where(X[:, :1] < 5.0, 0.05, 1.0)
    flat = np.array([5.0, -2.0, 0.5])
    V = flat + scatter * rng.standard_normal(X.shape)
    kwargs = {"alpha": "auto", "beta": "auto"}
    local = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, noise_spacing=0.5, noise_prior=1e-3, **kwargs)
    local.fit(X, V)
    plain = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **kwargs).fit(X, V)
    left, right = np.array([[2.0, 4.0, 3.0]]), np.array([[8.0, 4.0, 3.0]])
    for field, want_left, want_right in ((local, 0.05, 1.0), (plain, 0.72, 0.72)):
        for where, want in ((left, want_left), (right, want_right)):
            mean, std = field.predict(where, return_std=True)
            _, epistemic = field.predict(where, return_std=True, include_noise=False)
            if field is local:  # the squared residual about the mean also holds the mean's error
                want = np.sqrt(want**2 + (mean - flat) ** 2)
            np.testing.assert_allclose(np.sqrt(std**2 - epistemic**2), want, rtol=0.2)
    # far from every point the noise is the global 1/beta
    far = np.array([[60.0, 60.0, 60.0]])
    _, std = local.predict(far, return_std=True)
    _, epistemic = local.predict(far, return_std=True, include_noise=False)
    np.testing.assert_allclose(std**2 - epistemic**2, np.broadcast_to(1 / local.beta_, (1, 3)), rtol=1e-12)


def test_local_noise_partial_fit_equals_fit_and_forgets(data):
    X, V = data
    rng = np.random.default_rng(3)
    kwargs = {"alpha": "auto", "beta": "auto", "noise_spacing": NOISE_SPACING}
    batch = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **kwargs).fit(X, V)
    sequential = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **kwargs)
    for chunk in np.array_split(rng.permutation(len(X)), 4)[::-1]:
        sequential.partial_fit(X[chunk], V[chunk])
    Xq = rng.uniform(LOWER, UPPER, (50, 3))
    assert_close(
        sequential.predict(Xq, return_std=True)[1], batch.predict(Xq, return_std=True)[1], 1e-9, "std"
    )
    assert_close(sequential.evidence_.classes[0].moments, batch.evidence_.classes[0].moments, 1e-9, "moments")
    # forgetting decays the moments with the rest of the evidence
    forgetful = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, half_life=1.0, **kwargs).fit(X, V, time=0)
    forgetful.partial_fit(X[:1], V[:1], time=3.0)
    alone = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **kwargs).fit(X[:1], V[:1])
    expected = batch.evidence_.classes[0].moments / 8 + alone.evidence_.classes[0].moments
    assert_close(forgetful.evidence_.classes[0].moments, expected, 1e-12, "decayed moments")


def test_local_noise_grid_equals_points(data):
    X, V = data
    field = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, "auto", "auto", noise_spacing=NOISE_SPACING)
    field.fit(X, V)
    axes = [np.linspace(0, 10, 6), np.linspace(1, 7, 4), np.linspace(0, 6, 5)]
    mean, var = field.posterior_.predict_grid(axes)
    points = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    mean_p, std_p = field.predict(points, return_std=True)
    assert_close(mean.reshape(-1, 3), mean_p, 1e-8, "grid mean")
    assert_close(var.reshape(-1, 3), std_p**2, 20 * NOISE_CUTOFF, "grid variance")


def test_local_noise_saves_loads_and_refuses_mismatches(tmp_path, data):
    X, V = data
    field = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, "auto", "auto", noise_spacing=NOISE_SPACING)
    field.fit(X, V)
    field.save(tmp_path / "field.npz")
    loaded = BayesianDynamicField.load(tmp_path / "field.npz")
    Xq = X[:20] + 0.1
    np.testing.assert_array_equal(loaded.predict(Xq, return_std=True), field.predict(Xq, return_std=True))
    assert loaded.noise_spacing == NOISE_SPACING.tolist()
    plain = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA)
    grid, kernel = plain._setup()[:2]
    with pytest.raises(ValueError, match="moments do not fit"):
        plain.set_evidence(field.evidence_)
    with pytest.raises(ValueError, match="moments do not fit"):
        field.set_evidence(SectorEvidence.from_points(grid, kernel, X, V, sectors=Sectors()))
    with pytest.raises(ValueError, match="with local-noise moments to evidence without"):
        _ = field.evidence_ + SectorEvidence.from_points(grid, kernel, X, V, sectors=Sectors())


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"noise_spacing": 0.0}, "noise_spacing must be positive"),
        ({"noise_spacing": [1.0, 1.0]}, "noise_spacing must be a number or 3 numbers"),
        ({"noise_spacing": 0.01}, "more than 2000000; increase noise_spacing"),
        ({"noise_spacing": 1.0, "noise_prior": 0.0}, "noise_prior must be a positive number"),
        ({"noise_spacing": 1.0, "noise_prior": "auto"}, "noise_prior must be a positive number"),
    ],
)
def test_bad_local_noise_settings_are_clear_value_errors(change, message):
    field = BayesianDynamicField(LOWER, UPPER, SPACING, GAMMA, **change)
    with pytest.raises(ValueError, match=message):
        field.fit(np.ones((3, 3)), np.ones((3, 3)))


@pytest.mark.parametrize("directions", [1, 4])
def test_queries_gather_the_moments_as_laid_out_once(data, monkeypatch, directions):
    """A map keeps its noise moments as a LaneTable: a query does not lay out tens of MB a
    class again (it did, per class and per query: 271 against 52 ms on the demo's region at
    16 sectors, bench/RESULTS.md)."""
    X, V = data
    field = BayesianDynamicField(
        LOWER, UPPER, SPACING, GAMMA, "auto", "auto", noise_spacing=NOISE_SPACING, directions=directions
    ).fit(X, V)
    Xq = np.random.default_rng(1).uniform(LOWER, UPPER, (50, 3))
    axes = [np.linspace(0, 10, 6), np.linspace(1, 7, 4), np.linspace(0, 6, 5)]

    def answers():
        modes = field.predict_modes(Xq)
        return [*field.predict(Xq, return_std=True), modes.std, *field.posterior_.predict_grid(axes)]

    first = answers()  # lays out the query tables of the hinge and midpoint lattices

    def laid_out(*args):
        raise AssertionError("a query laid out a table")

    monkeypatch.setattr(features.LaneTable, "of", laid_out)
    for got, want in zip(answers(), first, strict=True):
        np.testing.assert_array_equal(got, want)
