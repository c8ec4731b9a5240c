"""The directional fit's cost against the one-class fit's, and what the searches add (issue 17).

    .venv/bin/python bench/bench_ratio.py [--rounds 5]

Fits of the Paris core lattice (the flight split's training points, track weights, alpha =
beta = auto), one class and 8 heading sectors, in one process. Every round runs each
configuration once, so that this machine's slow and fast spells fall on all of them:

- as shipped;
- each mode's search started at its own optimum, known from an earlier fit of the same
  data: what a search for the modes could do at best (one evaluation each);
- every class on its own support, all kept (``COVER`` 1.0, 20 supports);
- both;
- no search: alpha and beta given at the optima found (one class, and every class).

Prints medians over the rounds: fit times and the 8-sector fit over the one-class fit.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bdf import BayesianDynamicField, hyperparameters, ingest, posterior, sparse
from clients import samples
from clients.samples import PARIS_GAMMA, PARIS_SPACING_M


@contextlib.contextmanager
def configured(cover: float, supports: int, optima: dict | None):
    """``sparse.stencil.COVER`` and ``Stencil.SUPPORTS`` set, and with ``optima`` (class count ->
    ratio) the modes' searches started there instead of at the total's optimum."""
    saved = sparse.stencil.COVER, sparse.Stencil.SUPPORTS, posterior.hyperparameters.fit_evidence
    search = hyperparameters.fit_evidence

    def started_at_optimum(stencil, band, proj, v_sq, count, alpha, beta, start=None):
        if start is not None:  # a mode (the total starts cold)
            start = optima[round(float(count), 6)]
        return search(stencil, band, proj, v_sq, count, alpha, beta, start)

    sparse.stencil.COVER, sparse.Stencil.SUPPORTS = cover, supports
    if optima is not None:
        posterior.hyperparameters.fit_evidence = started_at_optimum
    try:
        yield
    finally:
        sparse.stencil.COVER, sparse.Stencil.SUPPORTS, posterior.hyperparameters.fit_evidence = saved


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    obs, lower, upper = samples.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    X, V, probe = obs.X[~test], obs.V[~test], obs.X[test][:1]
    weight = obs.subset(~test).track_weights(1 / np.asarray(PARIS_SPACING_M) ** 2)

    def fit(S, alpha="auto", beta="auto"):
        field = BayesianDynamicField(lower, upper, PARIS_SPACING_M, PARIS_GAMMA, alpha, beta, directions=S)
        field.fit(X, V, sample_weight=weight)
        field.predict_modes(probe)  # factorisations and variance densities
        return field

    one, eight = fit(1), fit(8)
    optima = {
        round(float(e.count), 6): m._solutions[0].lam
        for e, m in zip(eight.evidence_.classes, eight.posterior_.modes, strict=True)
    }
    hyper = {S: (f.posterior_.alpha, f.posterior_.beta) for S, f in ((1, one), (8, eight))}
    shipped = (sparse.stencil.COVER, sparse.Stencil.SUPPORTS)
    configurations = {
        "as shipped": (*shipped, None, False),
        "modes' searches started at their optima": (*shipped, optima, False),
        "every class on its own support, all kept": (1.0, 20, None, False),
        "both": (1.0, 20, optima, False),
        "no search (alpha, beta given at the optima)": (*shipped, None, True),
    }
    times = {name: {1: [], 8: []} for name in configurations}
    for r in range(args.rounds + 1):  # the first round warms the caches and the kept supports
        for name, (cover, supports, starts, given) in configurations.items():
            with configured(cover, supports, starts):
                for S in (1, 8):
                    t0 = time.perf_counter()
                    fit(S, *(hyper[S] if given else ("auto", "auto")))
                    if r:
                        times[name][S].append(time.perf_counter() - t0)
    print(f"`python bench/bench_ratio.py --rounds {args.rounds}`: medians of {args.rounds} rounds\n")
    print("| configuration | 1 class [s] | 8 sectors [s] | 8 sectors / 1 class |\n|---|---|---|---|")
    for name, t in times.items():
        one_s, eight_s = np.median(t[1]), np.median(t[8])
        print(f"| {name} | {one_s:.3f} | {eight_s:.3f} | {eight_s / one_s:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
