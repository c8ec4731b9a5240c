"""Evidence maximisation for alpha and beta (cross-validation of gamma and spacing: :mod:`bdf.crossval`).

Log marginal likelihood of Bayesian linear regression for one velocity component
(Bishop, PRML eq. 3.86), with ``A = alpha I + beta G``, ``G = Phi^T Phi``, ``b = Phi^T v``:

    ln p(v) = M/2 ln alpha + N/2 ln beta - beta/2 R - 1/2 ln|A| - N/2 ln 2 pi

where, writing ``lam = alpha / beta`` and ``m = (G + lam I)^-1 b`` (the posterior mean),
``R = ||v - Phi m||^2 + lam ||m||^2 = v^T v - b^T m`` and ``ln|A| = M ln beta +
ln|G + lam I|``. Everything comes from the additive statistics. For a fixed ratio ``lam``
the best beta is ``N / R`` in closed form, so with both hyperparameters "auto" a 1-D
search over ``lam`` with one Cholesky factorisation per step fits alpha and a separate
beta for each of the three components (they share ``lam``, hence one factorisation).
Factorisations are sparse (:mod:`bdf.linalg`): one symbolic analysis per stencil, then a
numeric factorisation of ``G + lam I`` per step.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from bdf import linalg

log = logging.getLogger(__name__)

#: Hyperparameters used for "auto" while a field holds no data (the paper's values).
EMPTY_ALPHA, EMPTY_BETA = 1e-2, 1e2
#: "auto" beta stays below this (noise std >= 1 mm/s): a component observed as exactly
#: constant (vertical speed 0 everywhere) would otherwise get beta -> inf and std -> 0.
MAX_AUTO_BETA = 1e6
#: The search range of ``log(lam / mean(diag G))``: any data; and its resolution (5 % in
#: lam: the evidence is flat there).
LOG_RANGE, LOG_TOLERANCE = (np.log(1e-10), np.log(1e4)), 0.05
#: Half-width (in log lam) of the window searched first around a known good ``lam``.
WINDOW = 2.5


@dataclass
class Solution:
    """One factorisation of ``G + lam I`` and what it gives."""

    lam: float
    factor: linalg.Factor
    weights: np.ndarray  # (M, 3) posterior means m for every component
    logdet: float  # ln|G + lam I|
    residual: np.ndarray  # (3,) R per component


def solve(stencil: linalg.Stencil, band, proj: np.ndarray, v_sq: np.ndarray, lam: float) -> Solution:
    """Factor ``G + lam I`` (``G`` given as its band on ``stencil``) and solve for the three
    components."""
    try:
        factor = stencil.factor_of(band, lam)
    except linalg.NotPositiveDefinite:
        raise linalg.NotPositiveDefinite(
            f"the precision matrix is not positive definite (alpha/beta = {lam:.3g}); "
            "increase alpha or decrease beta"
        ) from None
    weights = factor.solve(proj)
    residual = np.maximum(v_sq - np.einsum("mc,mc->c", proj, weights), 1e-300)
    return Solution(lam, factor, weights, factor.logdet(), residual)


def log_evidence(sol: Solution, alpha, beta, count: float) -> np.ndarray:
    """ln p(v | alpha, beta) per component for ``alpha / beta == sol.lam``."""
    M = len(sol.weights)
    alpha, beta = np.asarray(alpha, float), np.asarray(beta, float)
    return (
        0.5 * M * np.log(alpha)
        + 0.5 * count * np.log(beta)
        - 0.5 * beta * sol.residual
        - 0.5 * (M * np.log(beta) + sol.logdet)
        - 0.5 * count * np.log(2 * np.pi)
    )


def _hyper_for(sol: Solution, alpha, beta, count: float):
    """alpha, beta (3,) implied by ``sol.lam`` and whichever of them is fixed."""
    if isinstance(beta, str):
        beta = count / sol.residual if isinstance(alpha, str) else alpha / sol.lam
        # the evidence is concave in beta, so the constrained optimum is the bound
        beta = np.minimum(beta, MAX_AUTO_BETA)
    beta = np.broadcast_to(np.asarray(beta, float), (3,))
    return sol.lam * beta, beta


def _at_ratios(stencil, band, proj, v_sq, lams) -> list[Solution]:
    """The solutions at ratios ``lams`` (3,); ratios equal to rounding (fitted values
    stored and read back) share a factorisation."""
    same = np.isclose(lams[:, None], lams[None, :], rtol=1e-12, atol=0)
    first = [int(np.argmax(row)) for row in same]
    cache = {c: solve(stencil, band, proj, v_sq, lams[c]) for c in sorted(set(first))}
    return [cache[c] for c in first]


def _search(cost, start) -> int:
    """Minimise ``cost(log_lam)`` by Brent's bounded method over :data:`LOG_RANGE`, or, with
    a ``start``, first over a window around it, moved outwards while the optimum sits at
    its edge (the modes of a directional map start from their map's ratio).
    Returns the number of evaluations."""
    options = {"xatol": LOG_TOLERANCE}
    if start is None:
        return minimize_scalar(cost, bounds=LOG_RANGE, method="bounded", options=options).nfev
    lo, hi = max(start - WINDOW, LOG_RANGE[0]), min(start + WINDOW, LOG_RANGE[1])
    evaluations = 0
    while True:
        res = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options=options)
        evaluations += res.nfev
        if res.x - lo < 2 * LOG_TOLERANCE and lo > LOG_RANGE[0]:
            lo, hi = max(lo - 2 * WINDOW, LOG_RANGE[0]), lo + LOG_TOLERANCE
        elif hi - res.x < 2 * LOG_TOLERANCE and hi < LOG_RANGE[1]:
            lo, hi = hi - LOG_TOLERANCE, min(hi + 2 * WINDOW, LOG_RANGE[1])
        else:
            return evaluations


def fit_evidence(
    stencil, band, proj, v_sq, count, alpha, beta, start=None
) -> tuple[np.ndarray, np.ndarray, list]:
    """alpha (3,), beta (3,) and the factorisation(s) serving component 0, 1, 2.

    ``band``: ``G`` on ``stencil``. ``alpha``/``beta``: "auto" or 3-vectors. Fixed values
    need no search. "auto" for alpha shares ``lam`` over the components; a fixed alpha
    with "auto" beta searches each component on its own (up to three factorisations).
    ``start``: a ratio alpha / beta near the optimum, if one is known (the search starts
    there; the optimum found is the same to the search's tolerance).
    """
    auto_a, auto_b = isinstance(alpha, str), isinstance(beta, str)
    if (auto_a or auto_b) and count <= 0:
        log.info("no data: 'auto' hyperparameters take alpha=%g, beta=%g", EMPTY_ALPHA, EMPTY_BETA)
        alpha = EMPTY_ALPHA if auto_a else alpha
        beta = EMPTY_BETA if auto_b else beta
        auto_a = auto_b = False
    if not (auto_a or auto_b):
        alpha_v = np.broadcast_to(np.asarray(alpha, float), (3,))
        beta_v = np.broadcast_to(np.asarray(beta, float), (3,))
        return alpha_v.copy(), beta_v.copy(), _at_ratios(stencil, band, proj, v_sq, alpha_v / beta_v)

    scale = max(float(np.mean(band[0])), 1e-300)
    groups = [[0], [1], [2]] if (auto_b and not auto_a) else [[0, 1, 2]]
    alpha_v, beta_v, sols = np.empty(3), np.empty(3), [None] * 3
    for comps in groups:
        best = [np.inf, None]

        def cost(log_lam, comps=comps, best=best):
            try:
                sol = solve(stencil, band, proj, v_sq, scale * np.exp(log_lam))
            except linalg.NotPositiveDefinite:
                return np.inf  # rounding at the smallest ratios: the search moves up
            a, b = _hyper_for(sol, alpha, beta, count)
            value = -float(np.sum(log_evidence(sol, a, b, count)[comps]))
            if value < best[0]:
                best[:] = value, sol
            return value

        evaluations = _search(cost, None if start is None else float(np.log(start / scale)))
        sol = best[1]
        a, b = _hyper_for(sol, alpha, beta, count)
        alpha_v[comps], beta_v[comps] = a[comps], b[comps]
        for c in comps:
            sols[c] = sol
        log.debug("evidence fit for components %s: lam=%.4g in %d steps", comps, sol.lam, evaluations)
    return alpha_v, beta_v, sols
