"""Cross-validation of the kernel (gamma), the hinge spacing and the heading resolution."""

from __future__ import annotations

import itertools
import logging

import numpy as np

from bdf import metrics
from bdf.grid import HingeGrid, noise_lattice
from bdf.kernel import DEFAULT_CUTOFF, Kernel
from bdf.posterior import Mixture, Modes, Posterior
from bdf.sectors import AUTO_DIRECTIONS, Sectors
from bdf.statistics import SectorEvidence
from bdf.validation import as_observations, as_positive, as_sample_weight

log = logging.getLogger(__name__)


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
    cutoff=DEFAULT_CUTOFF,
    directions=1,
):
    """Pick ``(spacing, gamma)`` from ``candidates``, and the heading resolution, by K-fold
    cross-validation.

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
    cutoff : float
        The kernel cutoff of every candidate (:mod:`bdf.features`; looser is faster).
    directions : int, sequence of int, or "auto"
        Heading sectors (:mod:`bdf.sectors`): each candidate with each count ("auto":
        :data:`AUTO_DIRECTIONS`). The MSLL is the mixture's
        (:func:`bdf.metrics.mixture_msll`), the RMSE its mean's; ``cond_rmse`` (reported) is
        the RMSE of the mode of the heading each held-out row flies.

    Returns
    -------
    best : dict
        The winning row of ``table``.
    table : list of dict
        Per candidate and heading resolution: spacing, gamma, hinges, directions, rmse,
        msll, cond_rmse (means over folds).
    """
    if score not in ("msll", "rmse"):
        raise ValueError(f"score must be 'msll' or 'rmse', got {score!r}")
    X, V = as_observations(X, V)
    weight = np.ones(len(X)) if sample_weight is None else as_sample_weight(sample_weight, len(X))
    if n_splits < 2:
        raise ValueError(f"n_splits must be at least 2, got {n_splits}")
    lattice = None if noise_spacing is None else noise_lattice(lower, upper, noise_spacing)
    if isinstance(directions, str) and directions != "auto":
        raise ValueError(f'directions must be a count, counts or "auto", got {directions!r}')
    counts = AUTO_DIRECTIONS if isinstance(directions, str) else directions
    resolutions = [Sectors(int(S)) for S in np.atleast_1d(counts)]
    noise_prior = as_positive(noise_prior, "noise_prior")
    fold = folds(len(X), n_splits, groups, seed)

    table = []
    for (spacing, gamma), sectors in itertools.product(candidates, resolutions):
        grid = HingeGrid(lower, upper, spacing)
        kernel = Kernel(tuple(np.broadcast_to(np.asarray(gamma, float), (3,))), cutoff)
        parts = [
            SectorEvidence.from_points(
                grid,
                kernel,
                X[f],
                V[f],
                None,
                weight[f],
                sectors=sectors,
                noise_lattice=lattice,
            )
            for f in (fold == k for k in range(n_splits))
        ]
        total = parts[0]
        for part in parts[1:]:
            total = total + part
        rmses, mslls, conditional = [], [], []
        for k in range(n_splits):
            test = fold == k
            evidence, rest = total - parts[k], (alpha, beta, lattice, noise_prior)
            if sectors.classes == 1:
                post = Posterior(grid, kernel, evidence.classes[0], *rest)
            else:
                post = Mixture(grid, kernel, evidence, *rest, sectors)
            scores = held_out_scores(post.predict_modes(X[test]), sectors, V[test], V[~test])
            rmses.append(scores["rmse"])
            conditional.append(scores["cond_rmse"])
            mslls.append(scores["mixture_msll"])
        row = {
            "spacing": np.broadcast_to(spacing, (3,)).tolist(),
            "gamma": list(kernel.gamma),
            "hinges": grid.size,
            "cutoff": cutoff,
            "directions": sectors.directions,
            "rmse": float(np.mean(rmses)),
            "msll": float(np.mean(mslls)),
            "cond_rmse": float(np.mean(conditional)),
        }
        log.info("cross-validation %s", row)
        table.append(row)
    best = min(table, key=lambda r: r[score])
    return best, table


def folds(n: int, n_splits: int, groups=None, seed: int = 0) -> np.ndarray:
    """The fold (0 to ``n_splits`` - 1) of each of ``n`` rows: rows at random, or whole
    ``groups`` (n,) at random (``ValueError`` if there are fewer groups than folds)."""
    rng = np.random.default_rng(seed)
    if groups is None:
        return rng.permutation(n) % n_splits
    labels, inverse = np.unique(np.asarray(groups), return_inverse=True)
    if len(labels) < n_splits:
        raise ValueError(f"{len(labels)} groups cannot fill {n_splits} folds")
    return (rng.permutation(len(labels)) % n_splits)[inverse]


def held_out_scores(modes: Modes, sectors: Sectors, V: np.ndarray, V_train: np.ndarray) -> dict:
    """How a map's :class:`~bdf.posterior.Modes` at held-out rows predict their velocities
    ``V``: RMSE and MSLL of the mixture's moments, the mixture's MSLL
    (:func:`bdf.metrics.mixture_msll`), and the RMSE of the mode of each row's own heading
    (:meth:`~bdf.posterior.Modes.flown`); the MSLLs against the training rows' ``V_train``
    mean and std."""
    mean, std = modes.answer(sectors)
    mu, sd = V_train.mean(0), V_train.std(0)
    return {
        "rmse": float(metrics.rmse(V, mean)),
        "msll": float(metrics.msll(V, mean, std, mu, sd)),
        "mixture_msll": float(metrics.mixture_msll(V, modes.share, modes.mean, modes.std, mu, sd)),
        "cond_rmse": float(metrics.rmse(V, modes.flown(sectors, V)[0])),
    }
