"""Hyperparameters: evidence maximisation for alpha and beta, cross-validation for gamma and spacing.

Log marginal likelihood of Bayesian linear regression for one velocity component
(Bishop, PRML eq. 3.86), with ``A = alpha I + beta G``, ``G = Phi^T Phi``, ``b = Phi^T v``:

    ln p(v) = M/2 ln alpha + N/2 ln beta - beta/2 R - 1/2 ln|A| - N/2 ln 2 pi

where, writing ``lam = alpha / beta`` and ``m = (G + lam I)^-1 b`` (the posterior mean),
``R = ||v - Phi m||^2 + lam ||m||^2 = v^T v - b^T m`` and ``ln|A| = M ln beta +
ln|G + lam I|``. Everything comes from the additive statistics. For a fixed ratio ``lam``
the best beta is ``N / R`` in closed form, so with both hyperparameters "auto" a 1-D
search over ``lam`` with one Cholesky factorisation per step fits alpha and a separate
beta for each of the three components (they share ``lam``, hence one factorisation).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from scipy.optimize import minimize_scalar

from bdf import features, metrics, noise
from bdf._blas import threads_for
from bdf._validate import as_observations, as_positive, as_sample_weight
from bdf.grid import HingeGrid
from bdf.stats import Evidence

log = logging.getLogger(__name__)

#: Hyperparameters used for "auto" while a field holds no data (the paper's values).
EMPTY_ALPHA, EMPTY_BETA = 1e-2, 1e2
#: "auto" beta stays below this (noise std >= 1 mm/s): a component observed as exactly
#: constant (vertical speed 0 everywhere) would otherwise get beta -> inf and std -> 0.
MAX_AUTO_BETA = 1e6


@dataclass
class Solution:
    """One factorisation ``G + lam I = U^T U`` and what it gives."""

    lam: float
    factor: np.ndarray  # upper Cholesky factor U, Fortran order (what LAPACK takes without a copy)
    weights: np.ndarray  # (M, 3) posterior means m for every component
    logdet: float  # ln|G + lam I|
    residual: np.ndarray  # (3,) R per component


def solve(gram: np.ndarray, proj: np.ndarray, v_sq: np.ndarray, lam: float, out=None) -> Solution:
    """Factor ``gram + lam I`` (float64 Cholesky, in place) and solve for the three components.

    ``out``: an M x M buffer to factor in (a search reuses two instead of allocating,
    and faulting in, a fresh M^2 array per step); ``gram`` itself when it is not needed
    afterwards.
    """
    a = gram.copy() if out is None else out
    if out is not None and out is not gram:
        np.copyto(a, gram)
    a.flat[:: len(a) + 1] += lam
    # the transpose of a C-order symmetric matrix is itself in Fortran order: no copy
    with threads_for(len(a)):
        factor, info = sla.lapack.dpotrf(a.T, lower=0, overwrite_a=1, clean=1)
        if info != 0:
            raise ValueError(
                f"the precision matrix is not positive definite (alpha/beta = {lam:.3g}); "
                "increase alpha or decrease beta"
            )
        weights, info = sla.lapack.dpotrs(factor, proj, lower=0)
    residual = np.maximum(v_sq - np.einsum("mc,mc->c", proj, weights), 1e-300)
    logdet = 2.0 * float(np.sum(np.log(np.diag(factor))))
    return Solution(lam, factor, weights, logdet, residual)


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


def fit_evidence(gram, proj, v_sq, count, alpha, beta) -> tuple[np.ndarray, np.ndarray, list]:
    """alpha (3,), beta (3,) and the factorisation(s) serving component 0, 1, 2.

    ``alpha``/``beta``: "auto" or 3-vectors. Fixed values need no search. "auto" for
    alpha shares ``lam`` over the components; a fixed alpha with "auto" beta searches
    each component on its own (up to three factorisations). With fixed values ``gram``
    is factored in place: the caller must not read it afterwards.
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
        lams = alpha_v / beta_v
        unique = np.unique(lams)
        # the last factorisation may take the Gram matrix itself: nothing reads it after
        cache = {lam: solve(gram, proj, v_sq, lam, out=gram if lam == unique[-1] else None) for lam in unique}
        return alpha_v.copy(), beta_v.copy(), [cache[lam] for lam in lams]

    scale = max(float(np.mean(np.diag(gram))), 1e-300)
    groups = [[0], [1], [2]] if (auto_b and not auto_a) else [[0, 1, 2]]
    alpha_v, beta_v, sols = np.empty(3), np.empty(3), [None] * 3
    for comps in groups:
        # two buffers: the best factorisation so far stays in one, the next step uses the other
        buffers, best = [np.empty_like(gram), np.empty_like(gram)], [np.inf, None]

        def cost(log_lam, comps=comps, buffers=buffers, best=best):
            in_use = best[1] is not None and np.shares_memory(best[1].factor, buffers[0])
            scratch = buffers[1] if in_use else buffers[0]
            sol = solve(gram, proj, v_sq, scale * np.exp(log_lam), out=scratch)
            a, b = _hyper_for(sol, alpha, beta, count)
            value = -float(np.sum(log_evidence(sol, a, b, count)[comps]))
            if value < best[0]:
                best[:] = value, sol
            return value

        res = minimize_scalar(
            cost, bounds=(np.log(1e-10), np.log(1e4)), method="bounded", options={"xatol": 0.05}
        )  # 5% in lam: the evidence is flat there
        sol = best[1]
        a, b = _hyper_for(sol, alpha, beta, count)
        alpha_v[comps], beta_v[comps] = a[comps], b[comps]
        for c in comps:
            sols[c] = sol
        log.debug("evidence fit for components %s: lam=%.4g in %d steps", comps, sol.lam, res.nfev)
        del buffers[:]
    return alpha_v, beta_v, sols


def cross_validate(
    X,
    V,
    lower,
    upper,
    candidates,
    *,
    n_splits=5,
    groups=None,
    sample_weight=None,
    alpha="auto",
    beta="auto",
    score="msll",
    seed=0,
    noise_spacing=None,
    noise_prior=0.1,
):
    """Pick ``(spacing, gamma)`` from ``candidates`` by K-fold cross-validation.

    Evidence is additive, so each candidate builds one increment per fold and trains on
    ``total - fold``: one pass over the data per candidate, whatever ``n_splits``.

    Parameters
    ----------
    candidates : iterable of (spacing, gamma)
        Each a number or 3 numbers per axis.
    groups : (N,) or None
        Keep each group (e.g. a flight) within one fold, so the score measures prediction
        away from the tracks seen, not interpolation along them.
    sample_weight : (N,) or None
        Likelihood weights of the training points (see :func:`bdf.ingest.track_weights`).
    score : "msll" or "rmse"
        What to minimise (averaged over the three components).
    noise_spacing, noise_prior
        Local noise for every candidate, as in :class:`bdf.BayesianDynamicField`.

    Returns
    -------
    best : dict
        The winning row of ``table``.
    table : list of dict
        Per candidate: spacing, gamma, hinges, rmse, msll (means over folds).
    """
    from bdf.field import Posterior  # bdf.field imports this module

    if score not in ("msll", "rmse"):
        raise ValueError(f"score must be 'msll' or 'rmse', got {score!r}")
    X, V = as_observations(X, V)
    weight = np.ones(len(X)) if sample_weight is None else as_sample_weight(sample_weight, len(X))
    if n_splits < 2:
        raise ValueError(f"n_splits must be at least 2, got {n_splits}")
    lattice = None if noise_spacing is None else noise.noise_lattice(lower, upper, noise_spacing)
    noise_prior = as_positive(noise_prior, "noise_prior")
    rng = np.random.default_rng(seed)
    if groups is None:
        fold = rng.permutation(len(X)) % n_splits
    else:
        labels, inverse = np.unique(np.asarray(groups), return_inverse=True)
        if len(labels) < n_splits:
            raise ValueError(f"{len(labels)} groups cannot fill {n_splits} folds")
        fold = (rng.permutation(len(labels)) % n_splits)[inverse]

    table = []
    for spacing, gamma in candidates:
        grid = HingeGrid(lower, upper, spacing)
        gamma_v = np.broadcast_to(np.asarray(gamma, float), (3,)).copy()
        parts = [
            Evidence.from_points(grid, gamma_v, X[f], V[f], None, weight[f], noise_lattice=lattice)
            for f in (fold == k for k in range(n_splits))
        ]
        total = parts[0]
        for part in parts[1:]:
            total = total + part
        rmses, mslls = [], []
        for k in range(n_splits):
            test = fold == k
            post = Posterior(
                grid,
                gamma_v,
                total - parts[k],
                alpha,
                beta,
                features.DEFAULT_CUTOFF,
                lattice,
                noise_prior,
            )
            mean, std = post.predict(X[test], return_std=True)
            train = V[~test]
            rmses.append(metrics.rmse(V[test], mean))
            mslls.append(metrics.msll(V[test], mean, std, train.mean(0), train.std(0)))
        row = {
            "spacing": np.broadcast_to(spacing, (3,)).tolist(),
            "gamma": gamma_v.tolist(),
            "hinges": grid.size,
            "rmse": float(np.mean(rmses)),
            "msll": float(np.mean(mslls)),
        }
        log.info("cross-validation %s", row)
        table.append(row)
    best = min(table, key=lambda r: r[score])
    return best, table
