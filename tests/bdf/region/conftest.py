"""Regions shared by the tests of bdf.region."""

import numpy as np
import pytest

from bdf.region.spec import RegionSpec

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
