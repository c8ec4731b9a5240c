import numpy as np
import pytest

LOWER = np.array([0.0, 0.0, 0.0])
UPPER = np.array([10.0, 8.0, 6.0])
SPACING = np.array([2.0, 2.0, 1.5])
GAMMA = np.array([0.3, 0.2, 0.5])


def flow(X):
    """A smooth 3D velocity field for synthetic data."""
    return np.stack([np.sin(X[:, 0]), np.cos(X[:, 1]), 0.1 * X[:, 2]], axis=1)


@pytest.fixture
def data():
    rng = np.random.default_rng(0)
    X = rng.uniform(LOWER - 1, UPPER + 1, (300, 3))
    V = flow(X) + 0.1 * rng.standard_normal(X.shape)
    return X, V


def dense_features(X, hinges, gamma, noise_std=None):
    """Phi computed directly from the kernel (expected kernel if noise_std is given)."""
    diff2 = (X[:, None, :] - hinges[None]) ** 2
    if noise_std is None:
        return np.exp(-(diff2 * gamma).sum(-1))
    spread = 1 + 2 * gamma * noise_std[:, None, :] ** 2
    return np.prod(spread**-0.5 * np.exp(-gamma * diff2 / spread), axis=-1)


def dense_weight(X, Q, gamma, sample_weight=None):
    """The data's weight within the kernel's reach of each query point, directly:
    ``sum_i w_i exp(-sum_d gamma_d (q_d - x_id)^2)``."""
    w = np.ones(len(X)) if sample_weight is None else np.asarray(sample_weight, float)
    return np.array([w @ np.exp(-(((q - X) ** 2) @ np.asarray(gamma, float))) for q in Q])
