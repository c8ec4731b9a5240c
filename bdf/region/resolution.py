"""A region's heading resolution chosen by its data (``directions: "auto"``).

A fit of such a region (all its rows at once: ``POST /v1/regions/{name}/fit``, the demo)
cross-validates each count of :data:`bdf.sectors.AUTO_DIRECTIONS` on its rows, in
:data:`bdf.region.spec.CHOICE_FOLDS` folds grouped by track (a held-out flight is traffic
the map has not seen, not the next second of a flight it has), and keeps the fewest
sectors whose held-out mixture MSLL is within one standard error of the best (the
one-standard-error rule: Hastie, Tibshirani and Friedman, *The Elements of Statistical
Learning*, 7.10): a query costs in proportion to the classes, so finer sectors must earn
it. Each count's map of all the rows is computed first, its evidence search started at
the optimum of the count before (:func:`_start_from`: fewer factorisations, counted by
``bench/bench_directions.py --directions auto``), and the folds start theirs at its own optimum; it
is kept on disk, so that one count's evidence and maps are in memory at a time; the chosen
count's is the fit's map.

Uploads before any fit are split into :data:`bdf.region.spec.AUTO_FIRST_DIRECTIONS`
sectors: the store keeps no rows, so evidence is binned once, by the count in force.
"""

from __future__ import annotations

import contextlib
import logging
import tempfile
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from bdf.crossval import folds, held_out_scores
from bdf.posterior import Mixture, Posterior
from bdf.region.evidence import accepted_rows, accepted_rows_increments, increments, region_total
from bdf.region.map import RegionMap, compute_posterior, decode_posterior, encode_posterior, region_field
from bdf.region.spec import CHOICE_FOLDS, DirectionsScore, RegionSpec
from bdf.sectors import AUTO_DIRECTIONS, Sectors

log = logging.getLogger(__name__)
#: The folds are drawn with this seed: the same rows choose the same way.
CHOICE_SEED = 0


class Choice(NamedTuple):
    """A fit of a region of ``directions: "auto"``: the spec with the chosen model and
    scores, and what the fit stores and serves for it."""

    spec: RegionSpec
    increments: dict
    summary: dict
    posterior: Posterior | Mixture | None  # None: no row accepted


def choose_directions(
    spec: RegionSpec, rows: tuple, progress: Callable[[float], None] | None = None
) -> Choice:
    """The heading resolution of ``rows`` (:func:`bdf.region.evidence.checked_rows`) for a
    region of ``directions: "auto"``, with that resolution's map of all of them. Rows in
    fewer than :data:`CHOICE_FOLDS` tracks (an untracked row is its own) cannot be
    cross-validated: they keep the spec's model, and no scores."""
    X, V, noise, weight, *tracks = rows
    keep, weights, _, _ = accepted_rows(spec, X, V, noise, weight, *tracks)
    fold = _folds(tracks[0] if tracks else None, keep)
    if fold is None:
        kept = spec.with_directions(spec.model_directions)
        return Choice(kept, *_fit(kept, rows))
    steps = len(AUTO_DIRECTIONS) * (1 + CHOICE_FOLDS)
    spilled, scores, start = {}, [], None
    with contextlib.ExitStack() as files:
        for i, S in enumerate(AUTO_DIRECTIONS):
            candidate = spec.with_directions(S)
            tiles, _, full = _fit(candidate, rows, _start_from(start, S))
            total = region_total(candidate, {key: inc.evidence for key, inc in tiles.items()})
            start = full.next_start
            # one candidate's evidence and maps in memory at a time: its map waits on disk
            spilled[S] = files.enter_context(tempfile.TemporaryFile())
            spilled[S].write(encode_posterior(full))
            del tiles, full
            _report(progress, (i * (1 + CHOICE_FOLDS) + 1) / steps)
            held_out = []
            for k in range(CHOICE_FOLDS):
                test = fold == k
                part = increments(
                    candidate,
                    X[test],
                    V[test],
                    input_noise_std=None if noise is None else noise[test],
                    sample_weight=None if weights is None else weights[test],
                )
                train = total - region_total(candidate, {key: inc.evidence for key, inc in part.items()})
                post = region_field(candidate).set_evidence(train, start=start, settle=False)
                modes = RegionMap(candidate, post.posterior_.compact()).predict_modes(X[test])
                scored = held_out_scores(modes, candidate.sectors, V[test], V[keep & ~test])
                held_out.append([scored[name] for name in ("mixture_msll", "msll", "cond_rmse")])
                _report(progress, (i * (1 + CHOICE_FOLDS) + 2 + k) / steps)
            scores.append((S, np.array(held_out)))
        chosen = _fewest_within_one_se(scores)
        spilled[chosen].seek(0)
        post = decode_posterior(spilled[chosen].read())
    table = tuple(
        DirectionsScore(
            directions=S,
            mixture_msll=float(s[:, 0].mean()),
            mixture_msll_se=float(s[:, 0].std(ddof=1) / np.sqrt(len(s))),
            msll=float(s[:, 1].mean()),
            conditional_rmse_mps=float(s[:, 2].mean()),
            chosen=S == chosen,
        )
        for S, s in scores
    )
    log.info("region %s: %d heading sectors chosen, %s", spec.name, chosen, [t.model_dump() for t in table])
    spec = spec.with_directions(chosen, table)
    tiles, summary = accepted_rows_increments(spec, *rows)  # what the fit stores: cheap to redo
    return Choice(spec, tiles, summary, post)


def _fit(spec: RegionSpec, rows: tuple, start=None) -> tuple[dict, dict, Posterior | Mixture | None]:
    """The tile increments of ``rows``, their summary, and the map of them (None: no row
    accepted), its evidence search started at ``start``."""
    tiles, summary = accepted_rows_increments(spec, *rows)
    if summary["accepted"] == 0:
        return tiles, summary, None
    total = region_total(spec, {k: i.evidence for k, i in tiles.items()})
    return tiles, summary, compute_posterior(spec, total, start, stored=False)


def _start_from(previous: np.ndarray | None, directions: int) -> np.ndarray | None:
    """Where the evidence search of ``directions`` sectors starts: at the optimum of the
    candidate before (``previous``: a row for the map with one class, each sector, the slow
    class), each sector at the row of the earlier sector that holds its centre. The optimum
    is the same from any start; from one near it the search takes fewer factorisations."""
    if previous is None:
        return None
    k = Sectors(len(previous) - 2).sector_of_heading(Sectors(directions).centres_deg)
    return np.concatenate([previous[:1], previous[1 + k], previous[-1:]])


def _folds(track: np.ndarray | None, keep: np.ndarray) -> np.ndarray | None:
    """Each row's fold (the rows of one track together, an untracked row on its own; -1:
    not accepted), or None if the accepted rows lie in fewer groups than folds."""
    own = -1 - np.arange(len(keep))
    group = (own if track is None else np.where(track >= 0, track, own))[keep]
    if len(np.unique(group)) < CHOICE_FOLDS:
        return None
    fold = np.full(len(keep), -1)
    fold[keep] = folds(len(group), CHOICE_FOLDS, group, CHOICE_SEED)
    return fold


def _fewest_within_one_se(scores: list[tuple[int, np.ndarray]]) -> int:
    """The fewest sectors whose mean held-out mixture MSLL (first column, per fold) is within
    one standard error of the best's."""
    means = {S: s[:, 0].mean() for S, s in scores}
    best = min(means, key=means.get)
    folds = dict(scores)[best][:, 0]
    bar = means[best] + folds.std(ddof=1) / np.sqrt(len(folds))
    return min(S for S, m in means.items() if m <= bar)


def _report(progress: Callable[[float], None] | None, fraction: float) -> None:
    if progress is not None:
        progress(fraction)
