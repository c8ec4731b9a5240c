"""Local noise: how much the flow scatters, place by place (heteroscedastic predictive noise).

The paper's noise is one precision ``beta`` per component, everywhere. Traffic scatters
very differently from place to place: vertical speeds are near zero in level cruise and
not on a climb-out; an approach path holds one heading, a crossing of departures and
arrivals does not. With ``noise_spacing`` set, a field also keeps kernel-weighted
moments of its data on a fine *noise lattice* of spacing ``s`` (per axis),

    a0(x) = sum_n w_n k(x, x_n),  a1(x) = sum_n w_n k(x, x_n) v_n,  a2(x) = sum_n w_n k(x, x_n) v_n^2,

with ``k(x, x') = sum_g exp(-|x - g|_s^2) exp(-|x' - g|_s^2)`` (a splat onto the lattice,
then a gather; ``|u|_s^2 = sum_d u_d^2 / s_d^2``, and ``k ~ C exp(-|x - x'|_s^2 / 2)``
with ``C = (pi / 2)^(3/2)``). The predictive noise variance at ``x`` is the local mean
squared residual about the posterior mean ``m(x)``, shrunk towards the global ``1/beta``:

    sigma^2(x) = (sum_n w_n k (v_n - m)^2 / C + kappa / beta) / (a0 / C + kappa)
               = ((a2 - 2 m a1 + m^2 a0) / C + kappa / beta) / (a0 / C + kappa)

``a0 / C`` counts the data near ``x`` (a point at ``x`` counts its weight); ``kappa``
(``noise_prior``) is the weight of the global noise, in the units of the sample
weights. Far from data ``sigma^2 = 1/beta``. The moments are sums over points, so they
are additive like the rest of the evidence (``partial_fit`` still equals ``fit``) and
decay with it. The posterior mean is unchanged: only the noise term of the predictive
variance becomes local.
"""

from __future__ import annotations

import numpy as np

from bdf import features
from bdf.grid import Lattice
from bdf.kernel import NOISE_CUTOFF

#: Channels of the moments: weight, weighted velocity (3), weighted squared velocity (3).
CHANNELS = 7
#: ``sum_g`` of two unit-spacing Gaussians of unit width: the smoother's peak (per 3 axes).
_PEAK = (np.pi / 2.0) ** 1.5


def moments(lattice: Lattice, X, V, weight) -> np.ndarray:
    """The moments increment of ``(X, V)`` with weights ``weight`` (n,): lattice + (7,)."""
    W = np.concatenate([weight[:, None], weight[:, None] * V, weight[:, None] * V * V], axis=1)
    return features.splat(lattice, X, W, 1.0 / lattice.step**2, cutoff=NOISE_CUTOFF)


def table(lattice: Lattice, moments: np.ndarray) -> features.LaneTable:
    """The moments (lattice + (7,)) as queries gather them: laid out once, not per query
    (a noise lattice is fine: tens of MB a class)."""
    return features.LaneTable.of(moments, features.lanes_for(lattice, 1.0 / lattice.step**2, NOISE_CUTOFF))


def noise_variance(lattice: Lattice, moments, X, mean, beta, prior):
    """sigma^2 at points ``X`` (n, 3) where the posterior mean is ``mean`` (n, 3); ``moments``:
    lattice values or their :func:`table`."""
    a = features.gather(lattice, X, moments, 1.0 / lattice.step**2, cutoff=NOISE_CUTOFF)
    return _shrunk(a, mean, beta, prior)


def noise_variance_grid(lattice: Lattice, moments, axes, mean, beta, prior):
    """sigma^2 on the grid ``axes`` (nx, ny, nz, 3); ``mean`` on the same grid."""
    a = features.gather_grid(lattice, axes, moments, 1.0 / lattice.step**2, cutoff=NOISE_CUTOFF)
    return _shrunk(a, mean, beta, prior)


def _shrunk(a, mean, beta, prior):
    a0, a1, a2 = a[..., :1], a[..., 1:4], a[..., 4:7]
    squares = np.maximum(a2 - 2.0 * mean * a1 + mean * mean * a0, 0.0)
    return (squares / _PEAK + prior / beta) / (np.maximum(a0, 0.0) / _PEAK + prior)
