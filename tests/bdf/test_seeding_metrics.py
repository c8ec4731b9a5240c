import numpy as np
import pytest
from scipy.spatial.distance import cdist

from bdf import metrics
from bdf.seeding import free_space_seeds


@pytest.mark.parametrize("method", ["sobol", "halton"])
def test_seeds_fill_the_box_and_keep_away_from_data(method):
    rng = np.random.default_rng(0)
    data = rng.uniform(0, 10, (50, 3))
    X, V = free_space_seeds([0, 0, 0], [10, 10, 10], 512, near=data, radius=1.0, method=method)
    assert 0 < len(X) < 512
    np.testing.assert_array_equal(V, 0.0)
    assert cdist(X, data).min() >= 1.0
    everything, _ = free_space_seeds([0, 0, 0], [10, 10, 10], 512, method=method)
    assert len(everything) == 512
    kept = cdist(everything, data).min(1) >= 1.0
    assert len(X) == kept.sum()  # exactly the candidates farther than the radius survive
    # low discrepancy: every octant holds 1/8 of the points (exactly, for Sobol's 2^9)
    octant = np.bincount((everything >= 5).astype(int) @ [1, 2, 4])
    assert np.abs(octant - 64).max() <= (0 if method == "sobol" else 3)


def test_seeding_rejects_bad_arguments():
    with pytest.raises(ValueError, match="method must be"):
        free_space_seeds([0, 0, 0], [1, 1, 1], 8, method="random")
    with pytest.raises(ValueError, match="must exceed lower"):
        free_space_seeds([0, 0, 0], [1, 0, 1], 8)
    with pytest.raises(ValueError, match="n must be at least 1"):
        free_space_seeds([0, 0, 0], [1, 1, 1], 0)


def test_metrics_on_known_values():
    y = np.array([[1.0, 2.0], [3.0, 4.0]])
    assert metrics.rmse(y, y + 2.0) == pytest.approx(2.0)
    np.testing.assert_allclose(metrics.rmse(y, y + np.array([[1.0, 0.0], [1.0, 0.0]]), axis=0), [1.0, 0.0])
    # the trivial model (training mean and std) has MSLL 0; a sharper correct one is negative
    assert metrics.msll(y, np.full_like(y, 2.5), np.full_like(y, 1.5), 2.5, 1.5) == pytest.approx(0.0)
    assert metrics.msll(y, y, np.full_like(y, 0.1), 2.5, 1.5) < -2.0
    rng = np.random.default_rng(0)
    z = rng.standard_normal(200_000)
    assert metrics.coverage(z, 0.0 * z, 1.0 + 0.0 * z) == pytest.approx(0.95, abs=0.003)
    assert metrics.coverage(z, 0.0 * z, 0.5 + 0.0 * z, level=0.5) == pytest.approx(0.2639, abs=0.003)


def test_metrics_reject_mismatched_shapes():
    with pytest.raises(ValueError, match="same shape"):
        metrics.rmse(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="std must be positive"):
        metrics.msll(np.zeros(2), np.zeros(2), np.zeros(2), 0.0, 1.0)
