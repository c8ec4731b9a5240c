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
Factorisations are sparse (:mod:`bdf.sparse`): one symbolic analysis per stencil, then a
numeric factorisation of ``G + lam I`` per step.

The search is Newton's method in ``x = ln lam`` on the evidence's slope and curvature,
both analytic given two traces. At fixed beta,
``d ln p / dx = (gamma_eff - alpha ||m||^2) / 2`` with ``gamma_eff = M - lam tr((G + lam I)^-1)``,
MacKay's effective number of parameters (:func:`_derivatives` has the other cases and the
curvature, which needs ``tr((G + lam I)^-2)`` and ``m^T (G + lam I)^-1 m``). The traces come
from the factorisation already made, by Hutchinson's estimator on :data:`PROBES` fixed
random sign vectors (one multi-column solve; about 1 % of error on ``gamma_eff``). With the
probes fixed, the curvature is the exact derivative of the estimated slope, so Newton's
method converges quadratically to the slope's root, and that root is "auto": a function of
the evidence alone, the same (to :data:`LOG_TOLERANCE`) from any start. A map refreshed
after an upload starts at its previous optimum: a few factorisations reach the new one
(the first step's error is the curvature's change over it; ``bench/bench_stream.py``
counts them).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import numpy as np

from bdf import sparse

log = logging.getLogger(__name__)


class Abandoned(Exception):
    """A posterior's computation given up because its caller no longer needs it
    (:func:`abandon_when`): a service's settling pass when a newer version waits."""


_abandon: ContextVar[Callable[[], bool] | None] = ContextVar("abandon", default=None)


@contextmanager
def abandon_when(stop: Callable[[], bool]) -> Iterator[None]:
    """Within the block, the searches and the variance of posteriors computed in this
    context raise :class:`Abandoned` at their next factorisation once ``stop()`` is true."""
    token = _abandon.set(stop)
    try:
        yield
    finally:
        _abandon.reset(token)


def check_abandoned() -> None:
    """Raise :class:`Abandoned` if this context's computation is no longer needed."""
    stop = _abandon.get()
    if stop is not None and stop():
        raise Abandoned("the computation was abandoned: its result is no longer needed")


#: Hyperparameters used for "auto" while a field holds no data (the paper's values).
EMPTY_ALPHA, EMPTY_BETA = 1e-2, 1e2
#: "auto" beta stays below this (noise std >= 1 mm/s): a component observed as exactly
#: constant (vertical speed 0 everywhere) would otherwise get beta -> inf and std -> 0.
MAX_AUTO_BETA = 1e6
#: The search range of ``log(lam / mean(diag G))``: its top. Its bottom is
#: :data:`FLOOR_PER_CUTOFF` times the kernel cutoff: ``G`` drops the pairs and tails below
#: the cutoff, so its smallest eigenvalues are truncation noise, and so is the evidence of a
#: ratio near them: there the factorisation's evidence can exceed the dense
#: eigendecomposition's by thousands of nats and put absurd modes between lanes
#: (``bench/bench_kernels.py`` shows it on a class of the synthetic city).
LOG_TOP = np.log(1e4)
FLOOR_PER_CUTOFF = 1e4
#: The search ends where Newton's step in ``ln lam`` is below this: the optimum is then
#: known to about this (quadratic convergence), so maps of the same data fitted from
#: different starts (one fit, or a refresh after many uploads) agree to about 1e-7 of
#: their velocities' scale.
LOG_TOLERANCE = 1e-7
#: Within this (in ln lam) above the range's floor the slopes are least reliable: a
#: previous optimum there is not a start, and a search ending there is made again
#: (:func:`fit_evidence`), so that "auto" does not depend on where the search started.
NEAR_FLOOR = np.log(1e3)
#: A converged search whose optimum has this much less evidence (nats) than a point it saw
#: was misled by the slope's estimate (:func:`fit_evidence`); about a nat is its noise.
MISLED_NATS = 10.0
#: A loose search (the last resort, :func:`_search`) stops where its next step would gain
#: less than this (nats, by the local quadratic): below one nat two hyperparameters are not
#: told apart (Kass and Raftery's "not worth more than a bare mention").
EVIDENCE_TOLERANCE = 1.0
#: The search's longest step (in ln lam), and its most factorisations.
MAX_STEP, MAX_EVALUATIONS = 4.0, 40
#: Random sign vectors of the trace estimate (fixed: the search is deterministic).
PROBES, PROBE_SEED = 64, 20261123


@dataclass
class Factorisation:
    """One factorisation of ``G + lam I`` and what it gives."""

    lam: float
    factor: sparse.Factor
    weights: np.ndarray  # (M, 3) posterior means m for every component
    logdet: float  # ln|G + lam I|
    residual: np.ndarray  # (3,) R per component


def solve(stencil: sparse.Stencil, band, proj: np.ndarray, v_sq: np.ndarray, lam: float) -> Factorisation:
    """Factor ``G + lam I`` (``G`` given as its band on ``stencil``) and solve for the three
    components."""
    try:
        factor = stencil.factor_of(band, lam)
    except sparse.NotPositiveDefinite:
        raise sparse.NotPositiveDefinite(
            f"the precision matrix is not positive definite (alpha/beta = {lam:.3g}); "
            "increase alpha or decrease beta"
        ) from None
    weights = factor.solve(proj)
    residual = np.maximum(v_sq - np.einsum("mc,mc->c", proj, weights), 1e-300)
    return Factorisation(lam, factor, weights, factor.logdet(), residual)


def log_evidence(sol: Factorisation, alpha, beta, count: float) -> np.ndarray:
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


def _hyper_for(sol: Factorisation, alpha, beta, count: float):
    """alpha, beta (3,) implied by ``sol.lam`` and whichever of them is fixed."""
    if isinstance(beta, str):
        beta = count / sol.residual if isinstance(alpha, str) else alpha / sol.lam
        # the evidence is concave in beta, so the constrained optimum is the bound
        beta = np.minimum(beta, MAX_AUTO_BETA)
    beta = np.broadcast_to(np.asarray(beta, float), (3,))
    if not isinstance(alpha, str):  # as given, not lam * beta to rounding
        return np.broadcast_to(np.asarray(alpha, float), (3,)), beta
    return sol.lam * beta, beta


def _at_ratios(stencil, band, proj, v_sq, lams) -> list[Factorisation]:
    """The solutions at ratios ``lams`` (3,); ratios equal to rounding (fitted values
    stored and read back) share a factorisation."""
    same = np.isclose(lams[:, None], lams[None, :], rtol=1e-12, atol=0)
    first = [int(np.argmax(row)) for row in same]
    cache = {c: solve(stencil, band, proj, v_sq, lams[c]) for c in sorted(set(first))}
    return [cache[c] for c in first]


def _probes(M: int) -> np.ndarray:
    """:data:`PROBES` random sign vectors (M, PROBES), the same for every call."""
    return np.random.default_rng(PROBE_SEED).choice([-1.0, 1.0], size=(M, PROBES))


def _derivatives(
    sol: Factorisation, a, b, count, comps, tied, profiled, probes
) -> tuple[float, float, float]:
    """Slope and curvature in ``x = ln lam`` of the cost (the negative log evidence summed
    over ``comps``) at ``sol``, with alpha ``a`` and beta ``b`` (3,) there, and MacKay's fixed
    point (the ``x`` his re-estimate gives). ``tied``: beta is ``alpha / lam`` with alpha
    fixed; ``profiled`` (3,): beta is at its optimum ``N / R`` (auto, below its cap).

    Per component, ``d ln p / dx = (gamma_eff - alpha n) / 2`` (``n = ||m||^2``), plus
    ``(beta R - N) / 2`` when beta is tied to a fixed alpha (``beta = alpha / lam``). With
    ``C = lam (G + lam I)^-1``, ``d gamma_eff / dx = -tr(C - C^2)`` and ``dn / dx = -2 lam q``
    (``q = m^T (G + lam I)^-1 m``), ``dR / dx = lam n``; beta at its optimum ``N / R`` moves
    with ``R``. The traces of ``C`` and ``C - C^2`` are Hutchinson estimates.
    """
    lam, M = sol.lam, len(sol.weights)
    solved = sol.factor.solve(np.concatenate([probes, sol.weights[:, comps]], axis=1))
    Y, W = solved[:, : probes.shape[1]], solved[:, probes.shape[1] :]
    c1 = lam * np.einsum("mp,mp->", probes, Y) / probes.shape[1]  # tr C
    c2 = lam**2 * np.einsum("mp,mp->", Y, Y) / probes.shape[1]  # tr C^2
    gamma = M - c1
    m = sol.weights[:, comps]
    n, q = np.einsum("mc,mc->c", m, m), np.einsum("mc,mc->c", m, W)
    a, b, R = a[comps], b[comps], sol.residual[comps]
    an = a * n
    if tied:
        rise = gamma - an + b * R - count
        drise = -(c1 - c2) + 2 * lam * a * q + an - b * R
    else:
        moved = np.divide(an * lam * n, R, out=np.zeros_like(R), where=profiled[comps])  # beta = N / R
        d_an = an - 2 * lam * a * q - moved
        rise = gamma - an
        drise = -(c1 - c2) - d_an
    # MacKay: alpha n = gamma_eff (alpha = lam beta), or with alpha fixed
    # beta ||v - Phi m||^2 = N - gamma_eff, where ||v - Phi m||^2 = R - lam n
    if tied:
        fixed = a[0] * (R[0] - lam * n[0]) / max(count - gamma, 1e-300)
    else:
        fixed = len(comps) * gamma / max(np.sum(b * n), 1e-300)
    return -0.5 * float(np.sum(rise)), -0.5 * float(np.sum(drise)), float(np.log(max(fixed, 1e-300)))


@dataclass
class Found:
    """Where a search (:func:`_search`) ended."""

    x: float  # the last point evaluated
    evaluations: int
    converged: bool  # a minimum of the cost or a bound, not a maximum nor the evaluations spent
    step: float  # the step it would take next from ``x`` (below LOG_TOLERANCE: settled)
    gain: float  # the nats Newton's step from ``x`` would gain (the local quadratic)
    #: the evaluations a loose search from the same start makes (the same points, up to
    #: where it stops: a prefix of this search's)
    loose_evaluations: int


def _search(evaluate, x: float, bounds: tuple[float, float], loose: bool = False) -> Found:
    """Find the optimum of ``x = ln lam`` from ``x``, within ``bounds``.

    ``evaluate(x)`` returns the cost's slope (NaN where the factorisation fails) and
    curvature, and MacKay's fixed point. Newton's step where the curvature is positive, or
    the fixed point where it is not or goes further the same way (far from the optimum,
    where the curvature changes, it is the better guess), inside the bracket the slopes
    have shown (bisecting it where a step would leave it), until a step is below
    :data:`LOG_TOLERANCE` (``loose``: or until Newton's step would gain less than
    :data:`EVIDENCE_TOLERANCE`).
    """
    lo, hi, loose_evaluations = -np.inf, np.inf, None
    for evaluations in range(1, MAX_EVALUATIONS + 1):
        slope, curvature, fixed_point = evaluate(x)
        log.debug("x=%.9f slope %.4g curvature %.4g fixed point %.4f", x, slope, curvature, fixed_point)
        if not np.isfinite(slope):  # not positive definite: more regularisation
            lo = x
            x = min(x + MAX_STEP, (x + min(hi, bounds[1])) / 2)
            continue
        if slope < 0:
            lo = max(lo, x)
        else:
            hi = min(hi, x)
        proposal = x - slope / curvature if curvature > 0 else fixed_point
        if (proposal - x) * (fixed_point - x) > 0 and abs(fixed_point - x) > abs(proposal - x):
            proposal = fixed_point  # far from the optimum the curvature changes: the longer step
        proposal = float(np.clip(proposal, x - MAX_STEP, x + MAX_STEP))
        if not lo < proposal < hi:
            proposal = (lo + hi) / 2 if np.isfinite(lo + hi) else x - np.sign(slope) * MAX_STEP
        proposal = float(np.clip(proposal, *bounds))
        newton = curvature > 0 and proposal == x - slope / curvature
        gain = slope**2 / (2 * curvature) if newton else (0.0 if proposal == x else np.inf)
        if loose_evaluations is None and (abs(proposal - x) < LOG_TOLERANCE or gain < EVIDENCE_TOLERANCE):
            loose_evaluations = evaluations
        if abs(proposal - x) < LOG_TOLERANCE or (loose and gain < EVIDENCE_TOLERANCE):
            return Found(x, evaluations, curvature > 0 or x in bounds, proposal - x, gain, loose_evaluations)
        x = proposal
    return Found(x, MAX_EVALUATIONS, False, 0.0, np.inf, loose_evaluations or MAX_EVALUATIONS)


@dataclass
class EvidenceFit:
    """What :func:`fit_evidence` found."""

    alpha: np.ndarray  # (3,)
    beta: np.ndarray  # (3,)
    solutions: list  # the factorisation serving component 0, 1, 2
    factorisations: int  # how many it took
    #: the hyperparameters are the evidence maximum (to LOG_TOLERANCE), not only within
    #: EVIDENCE_TOLERANCE of it (a search that need not settle, :func:`fit_evidence`)
    settled: bool
    gap: float  # nats the evidence lacks from its maximum (the local quadratic; 0 settled)
    next_start: np.ndarray  # (3,) ratios alpha / beta a next search starts at
    #: "auto" ended at the search's floor (within NEAR_FLOOR of it) or top: the evidence
    #: could not place alpha / beta inside the range
    at_bound: bool = False


def fit_evidence(
    stencil, band, proj, v_sq, count, alpha, beta, start=None, anchor=None, settle=True
) -> EvidenceFit:
    """alpha and beta at the evidence maximum, and the factorisations at them.

    ``band``: ``G`` on ``stencil``. ``alpha``/``beta``: "auto" or 3-vectors. Fixed values
    need no search. "auto" for alpha shares ``lam`` over the components; a fixed alpha
    with "auto" beta searches each component on its own.
    ``start``: a ratio alpha / beta near the optimum, one or per component, if one is
    known (the previous optimum of a map refreshed: the search starts there; the optimum
    found is the same to :data:`LOG_TOLERANCE`). ``anchor``: where a search without it
    starts (a ratio fixed by the evidence alone: a mode's, its map's; default the mean of
    ``G``'s diagonal). ``settle=False`` (with ``start``): the search from ``start`` may
    stop where the evidence lacks less than :data:`EVIDENCE_TOLERANCE` from its maximum
    (the map is fresh at once and calibrated to a nat; a search with ``settle`` from
    ``next_start`` then finds the maximum itself, typically in one factorisation fewer).
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
        ratios = alpha_v / beta_v
        sols = _at_ratios(stencil, band, proj, v_sq, ratios)
        return EvidenceFit(alpha_v.copy(), beta_v.copy(), sols, len({id(s) for s in sols}), True, 0.0, ratios)

    scale = max(float(np.mean(band[0])), 1e-300)
    bounds = (np.log(FLOOR_PER_CUTOFF * stencil.cutoff), LOG_TOP)
    groups = [[0], [1], [2]] if (auto_b and not auto_a) else [[0, 1, 2]]
    tied = not auto_a  # beta follows lam with alpha fixed
    probes = _probes(len(proj))
    starts = None if start is None else np.broadcast_to(np.asarray(start, float), (3,))
    alpha_v, beta_v, sols, factorisations = np.empty(3), np.empty(3), [None] * 3, 0
    settled, gap, next_start, at_bound = True, 0.0, np.empty(3), False
    for comps in groups:
        span = bounds
        if tied:  # beta = alpha / lam stays below its cap, so alpha stays the fixed one
            fixed = np.broadcast_to(np.asarray(alpha, float), (3,))[comps]
            least = float(np.log(fixed.min() / MAX_AUTO_BETA / scale))
            span = (max(bounds[0], least), max(bounds[1], least))

        def search(x0, loose=False, comps=comps, span=span):
            """One search from ``x0``: its last solution, the best it saw by the evidence
            (value, solution), where it ended (:class:`Found`), and the value at each point
            (x, value)."""
            latest, best, trail = [None], [np.inf, None], []

            def evaluate(x):
                check_abandoned()
                try:
                    sol = solve(stencil, band, proj, v_sq, scale * np.exp(x))
                except sparse.NotPositiveDefinite:
                    trail.append((x, np.inf))
                    return np.nan, np.nan, np.nan  # rounding at the smallest ratios: move up
                latest[0] = sol
                a, b = _hyper_for(sol, alpha, beta, count)
                value = -float(np.sum(log_evidence(sol, a, b, count)[comps]))
                trail.append((x, value))
                if value < best[0]:
                    best[:] = value, sol
                profiled = auto_a & auto_b & (b < MAX_AUTO_BETA)
                slope, curvature, fixed_point = _derivatives(sol, a, b, count, comps, tied, profiled, probes)
                return slope, curvature, fixed_point - np.log(scale)

            found = _search(evaluate, x0, span, loose)
            # the slope's estimate can mislead the search (truncation noise at the smallest
            # ratios) to far less evidence than it saw: not converged then
            if found.converged and latest[0] is not best[1]:
                a, b = _hyper_for(latest[0], alpha, beta, count)
                value = -float(np.sum(log_evidence(latest[0], a, b, count)[comps]))
                found.converged = value < best[0] + MISLED_NATS
            return latest[0], best, found, trail

        # From the previous optimum (warm), else from ``anchor`` (cold): the optimum they
        # converge to is the same. Near the floor the slopes are truncation noise: a warm
        # start there is not taken, a search that ends there is made again from the anchor,
        # and where no search converges away from it, the anchor's loose search (its best
        # evidence, stopping where a step gains less than a nat) is the answer. A warm search
        # that need not settle stops within a nat of the optimum.
        low = bounds[0] + NEAR_FLOOR
        cold = float(np.clip(0.0 if anchor is None else np.log(anchor / scale), *span))
        tries = [(cold, False)]
        if starts is not None:
            warm = float(np.clip(np.log(np.mean(starts[comps]) / scale), *span))
            if warm >= low and warm != cold:
                tries = [(warm, not settle), (cold, False)]
        factored, sol = False, None
        for x0, loose in tries:
            last, best, found, trail = search(x0, loose)
            factorisations += found.evaluations
            factored = factored or best[1] is not None
            if found.converged and found.x >= low:
                sol, ended = last, found
                break
        if sol is None and factored:
            # the anchor's loose search: the points of the cold search just made, up to where
            # it stops (no need to factor them again); its best by the evidence
            at, value = min(trail[: found.loose_evaluations], key=lambda point: point[1])
            if np.isfinite(value):
                sol = last if last is not None and last.lam == scale * np.exp(at) else None
                if sol is None:
                    sol = solve(stencil, band, proj, v_sq, scale * np.exp(at))
                    factorisations += 1
            ended = None  # the answer: no search would settle elsewhere
        if sol is None:  # no ratio in the range could be factored
            raise sparse.NotPositiveDefinite(
                f"the precision matrix is not positive definite at any alpha/beta in "
                f"[{scale * np.exp(bounds[0]):.3g}, {scale * np.exp(bounds[1]):.3g}]"
            )
        a, b = _hyper_for(sol, alpha, beta, count)
        alpha_v[comps], beta_v[comps] = a[comps], b[comps]
        for c in comps:
            sols[c] = sol
        next_start[comps] = sol.lam
        at = np.log(sol.lam / scale)
        at_bound = at_bound or at < bounds[0] + NEAR_FLOOR or at > bounds[1] - LOG_TOLERANCE
        if ended is not None and abs(ended.step) >= LOG_TOLERANCE:
            settled, gap = False, gap + ended.gain
            next_start[comps] = scale * np.exp(ended.x + ended.step)
        log.debug("evidence fit for components %s: lam=%.6g", comps, sol.lam)
    return EvidenceFit(alpha_v, beta_v, sols, factorisations, settled, gap, next_start, at_bound)
