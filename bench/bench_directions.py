"""Heading resolution: the demo's map with 8, 16, 24 and 32 sectors, and the mode of a heading.

The Paris flight split (20 % of flights held out, seed 0), the training flights' raw 1 Hz
rows with their ``track`` and ``t`` columns through the service's own path (the weights its
uploads give them, :func:`bench_tracks.library_map`), on the demo's lattice. Per number of
sectors, each in a fresh process (its peak RSS is the map's): the build, held-out MSLL of
the mixture's moments, mixture MSLL, and the conditional answer at the heading each held-out
row flies, two ways side by side: the two nearest sectors' modes pooled (the service's rule,
:func:`bdf.sectors.heading_mode`) and the sector's own mode (the rule before); with the linear
blend of the two modes (weights linear in angle, moments of the blend) for reference. Then
the map over its box as traffic can fly it (:func:`bench_tracks.plausibility`), and a
1,000-point query with the modes, in the library.

    python bench/bench_directions.py [--directions 8,16,24,32,auto] [--spread-share 0.5]
        [--noise-spacing 1000,1000,125 --noise-prior none,0.01,0.1] [--publish]

``auto``: the region's fit chooses among 8, 16, 24 and 32 by flight-grouped cross-validation
of the training rows (``bdf.region.resolution``); its build is the choice's, and its row
shows the scores that chose and the factorisations each count took (its map of all the
rows, then its folds; a count, so unlike the times the same on a busy machine).
``--spread-share``: each map with these values of :data:`bdf.posterior.CLASS_SPREAD_SHARE`
(how much of its class's spread a mode gains where its prior holds it; 0: none) instead of
the library's. ``--noise-spacing`` and ``--noise-prior``: each map with local noise
(:mod:`bdf.noise`) on that lattice at each prior weight ("none": the global noise, the
demo's). Every row also says what the region would store: its map and its tiles.
"""

from __future__ import annotations

import argparse
import itertools
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def conditional(sectors, test, modes, epistemic, mu, sd) -> dict:
    """The answer at each held-out row's own heading (slow rows: the slow class's mode, the
    same for all): the service's (:meth:`bdf.posterior.Modes.flown`), the sector's own mode,
    and the linear blend; and the service's cov95 where the noise is over 90 % of its
    variance (``epistemic``: the modes without noise), with the share of values there."""
    from bdf import metrics
    from bdf.sectors import mixture_moments

    V, rows = test.V, np.arange(len(test.V))
    heading = np.degrees(np.arctan2(V[:, 0], V[:, 1]))
    slow = np.hypot(V[:, 0], V[:, 1]) < sectors.slow_mps
    k0, k1, weight = sectors.nearest_two(heading)
    blend = np.zeros_like(modes.share)
    blend[rows, k0] += weight
    blend[rows, k1] += 1.0 - weight
    own = sectors.sector_of_heading(heading)
    answers = {
        "pooled": modes.flown(sectors, V),
        "own sector": (modes.mean[rows, own], modes.std[rows, own]),
        "linear blend": mixture_moments(blend, modes.mean, modes.std),
    }
    mean, std = answers["pooled"]
    noisy = epistemic.flown(sectors, V)[1] ** 2 < 0.1 * std**2
    out = {
        "pooled: cov95 where noise > 90 % of variance": float(
            metrics.coverage(V[noisy], mean[noisy], std[noisy])
        ),
        "values where noise > 90 %": float(noisy.mean()),
    }
    for name, (mean, std) in answers.items():
        mean = np.where(slow[:, None], modes.mean[:, -1], mean)
        std = np.where(slow[:, None], modes.std[:, -1], std)
        out[f"{name}: RMSE"] = float(metrics.rmse(V, mean))
        out[f"{name}: MSLL"] = float(metrics.msll(V, mean, std, mu, sd))
        out[f"{name}: cov95"] = float(metrics.coverage(V, mean, std))
    return out


def _counted_solves() -> list:
    """A list that gains an entry at each factorisation :mod:`bdf.hyperparameters` makes from
    now on in this process (each map runs in its own)."""
    from bdf import hyperparameters

    solves, solve = [], hyperparameters.solve
    hyperparameters.solve = lambda *args: solves.append(1) or solve(*args)
    return solves


def one(
    directions: int | str,
    spacing: list[float] | None = None,
    spread_share: float | None = None,
    noise: tuple[list[float], float] | None = None,
) -> dict:
    """The figures of the map with ``directions`` sectors (run in its own process); "auto":
    the sectors the region's fit chooses (:mod:`bdf.region.resolution`), with its scores.
    ``spacing`` (m, per axis): that lattice, gamma 1 / spacing^2, instead of the demo's;
    ``spread_share``: :data:`bdf.posterior.CLASS_SPREAD_SHARE`, instead of the library's;
    ``noise``: local noise (:mod:`bdf.noise`) of this lattice spacing and prior weight."""
    import resource

    from bench_tracks import library_increments, library_map, plausibility, split

    from bdf import metrics, posterior

    if spread_share is not None:
        posterior.CLASS_SPREAD_SHARE = spread_share
    from bdf.region.evidence import checked_rows
    from bdf.region.map import RegionMap, encode_posterior
    from bdf.region.resolution import choose_directions
    from bdf.region.spec import RegionSpec
    from bdf.sectors import AUTO_DIRECTIONS
    from clients import samples

    train, test, lower, upper = split()
    if spacing is None:
        spec = samples.paris_demo_region(lower, upper, directions=directions)
    else:
        spec = samples.paris_region(
            lower, upper, spacing, directions=directions, cutoff=samples.PARIS_REGION_CUTOFF
        )
    if noise is not None:
        spec = RegionSpec.model_validate(
            {**spec.model_dump(), "noise_spacing_m": noise[0], "noise_prior": noise[1]}
        )
    t0 = time.perf_counter()
    chose = {}
    if directions == "auto":
        solves, steps = _counted_solves(), []  # factorisations at each step of the fit
        choice = choose_directions(
            spec,
            checked_rows(train.X, train.V, track=train.flight, time=train.time),
            lambda _: steps.append(len(solves)),
        )
        per_step = np.diff([0, *steps]).reshape(len(AUTO_DIRECTIONS), -1)  # a count's map, then its folds
        spec, rmap = choice.spec, RegionMap(choice.spec, choice.posterior)
        chose = {
            "chosen": spec.model_directions,
            "CV mixture MSLL +- se (8/16/24/32)": " / ".join(
                f"{s.mixture_msll:.3f} +- {s.mixture_msll_se:.3f}" for s in spec.directions_scores
            ),
            "CV conditional RMSE (8/16/24/32)": " / ".join(
                f"{s.conditional_rmse_mps:.2f}" for s in spec.directions_scores
            ),
            "factorisations: maps of all rows / folds (8/16/24/32)": " / ".join(
                f"{row[0]}, {row[1:].sum()}" for row in per_step
            ),
        }
        increments = choice.increments
    else:
        increments = library_increments(spec, train, True)
        rmap = library_map(spec, train, True, increments)
    build_s = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    modes = rmap.predict_modes(test.X)
    mean, std, _ = rmap.predict(test.X, modes=modes)
    mu, sd = train.V.mean(0), train.V.std(0)
    Q = test.X[np.random.default_rng(0).choice(len(test.X), 1000, replace=False)]
    query = []
    for _ in range(5):
        t = time.perf_counter()
        rmap.predict(Q, modes=rmap.predict_modes(Q))
        query.append(time.perf_counter() - t)
    judged = plausibility(spec, rmap, train)
    return {
        "sectors": directions,
        "spread share": posterior.CLASS_SPREAD_SHARE,
        "local noise (spacing m; prior)": "none" if noise is None else f"{noise[0]}; {noise[1]}",
        **chose,
        "build [s]": build_s,
        "peak RSS [GB]": peak / 1e9,
        "held-out MSLL": float(metrics.msll(test.V, mean, std, mu, sd)),
        "mixture MSLL": metrics.mixture_msll(test.V, modes.share, modes.mean, modes.std, mu, sd),
        **conditional(
            spec.sectors,
            test,
            modes,
            rmap.posterior.predict_modes(spec.inside_points(test.X), include_noise=False),
            mu,
            sd,
        ),
        "worst ratio to bound": judged["worst ratio to bound"],
        "implausible voxels": judged["implausible voxels"],
        "1,000-point query with modes [ms]": 1e3 * min(query),
        # what a region stores: its map (encode_posterior) and its tiles (statistics and
        # their rounding residual, as large again)
        "stored map [MB]": len(encode_posterior(rmap.posterior)) / 1e6,
        "tiles [MB]": sum(2 * len(i.evidence.to_bytes()) for i in increments.values()) / 1e6,
    }


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--directions", default="8,16,24,32")
    parser.add_argument("--spacing", help="a lattice of this spacing (m, x,y,z; gamma 1 / spacing^2)")
    parser.add_argument(
        "--spread-share", help="values of bdf.posterior.CLASS_SPREAD_SHARE to run (comma-separated)"
    )
    parser.add_argument("--noise-spacing", help="local noise on a lattice of this spacing (m, x,y,z)")
    parser.add_argument(
        "--noise-prior", default="none", help="its prior weights (comma-separated; none: the global noise)"
    )
    parser.add_argument("--one", help=argparse.SUPPRESS)  # a child: one map, JSON out
    parser.add_argument("--publish", action="store_true", help="append the report to bench/RESULTS.md")
    args = parser.parse_args()
    spacing = None if args.spacing is None else [float(v) for v in args.spacing.split(",")]
    shares = [None] if args.spread_share is None else [float(v) for v in args.spread_share.split(",")]
    priors = args.noise_prior.split(",")
    if args.one:
        directions = args.one if args.one == "auto" else int(args.one)
        noise = None
        if priors[0] != "none":
            noise = ([float(v) for v in args.noise_spacing.split(",")], float(priors[0]))
        print(json.dumps(one(directions, spacing, shares[0], noise)))
        return
    from bench_core import publish, rows_table

    rows = []
    for share, prior in itertools.product(shares, priors):
        for directions in args.directions.split(","):
            out = subprocess.run(
                [
                    sys.executable,
                    __file__,
                    "--one",
                    str(directions),
                    *(["--spacing", args.spacing] if spacing else []),
                    *(["--spread-share", str(share)] if share is not None else []),
                    *(
                        ["--noise-spacing", args.noise_spacing, "--noise-prior", prior]
                        if prior != "none"
                        else []
                    ),
                ],
                capture_output=True,
                text=True,
                cwd=ROOT,
            )
            if out.returncode:
                raise RuntimeError(out.stderr[-3000:])
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(rows[-1], flush=True)
    command = (
        f"python bench/bench_directions.py --directions {args.directions}"
        + (f" --spacing {args.spacing}" if spacing else "")
        + (f" --spread-share {args.spread_share}" if args.spread_share else "")
        + (
            f" --noise-spacing {args.noise_spacing} --noise-prior {args.noise_prior}"
            if args.noise_spacing
            else ""
        )
    )
    lines = [
        f"\n## Heading resolution ({time.strftime('%Y-%m-%d')}, `{command}`)\n",
        "Paris flight split, raw rows with track and t (the service's weights), "
        + (f"a {args.spacing} m lattice; " if spacing else "the demo's lattice; ")
        + "conditional: the answer at each held-out row's own heading; each map in a fresh process.",
        rows_table(rows),
    ]
    publish(lines, args.publish)


if __name__ == "__main__":
    main()
