"""Quasi-Monte Carlo free-space seeding (paper III-D).

Space where no vehicle was seen is, for a static map, space where the velocity is zero.
Zero-velocity pseudo-observations spread evenly (Sobol or Halton) over a box tell the
model so; candidates within ``radius`` of real data are dropped so they never contradict it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import qmc

from bdf.validation import as_points, as_vector3


def free_space_seeds(lower, upper, n, near=None, radius=0.0, *, method="sobol", seed=0):
    """Zero-velocity pseudo-observations in the box ``[lower, upper]``.

    Parameters
    ----------
    n : int
        Number of QMC candidates (Sobol: rounded up to a power of two for balance).
    near : (N, 3) or None
        Real observation positions; candidates closer than ``radius`` to any are dropped.
    radius : float or 3 numbers
        Exclusion radius (per axis: distances are measured after dividing by it).
    method : "sobol" or "halton"

    Returns
    -------
    X, V : (K, 3) arrays, K <= n; V is all zeros.
    """
    lower, upper = as_vector3(lower, "lower"), as_vector3(upper, "upper")
    if np.any(upper <= lower):
        raise ValueError(f"upper {upper.tolist()} must exceed lower {lower.tolist()}")
    if int(n) < 1:
        raise ValueError(f"n must be at least 1, got {n}")
    if method == "sobol":
        unit = qmc.Sobol(3, seed=seed).random_base2(int(np.ceil(np.log2(int(n)))))
    elif method == "halton":
        unit = qmc.Halton(3, seed=seed).random(int(n))
    else:
        raise ValueError(f"method must be 'sobol' or 'halton', got {method!r}")
    X = qmc.scale(unit, lower, upper)
    if near is not None and np.any(np.asarray(radius) > 0):
        scale = as_vector3(radius, "radius", positive=True)
        tree = cKDTree(as_points(near, "near") / scale)
        dist, _ = tree.query(X / scale, k=1, distance_upper_bound=1.0)
        X = X[~np.isfinite(dist)]
    return X, np.zeros_like(X)
