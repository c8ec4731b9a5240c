"""The demo region's lattice: flight-grouped cross-validation of hinge spacings and kernels.

    .venv/bin/python bench/bench_lattice.py [--cutoff 1e-9] [--directions 8] [--gammas 1] [--no-append]

Candidates: 2 km horizontally (the finest the region must reach) by 500 m and 1 km
vertically, each with gamma = 1 or 2 (``--gammas``) times 1 / spacing^2, and today's 4 km
core lattice as the reference. Data: the training flights of the core benchmark's flight
split (20 % of whole flights held out, seed 0); 5 folds of whole flights; track weights per
lattice (each flight weighs 1 per lattice cell it crosses); alpha = beta = auto; one class,
or ``--directions`` heading sectors (the demo's map: the mixture's MSLL). Per
candidate also the prior std's ripple between hinges (``1 - min / max`` of
``sqrt(phi(x)^T phi(x))`` over a lattice cell): a kernel narrow for its lattice shows the
lattice as a pattern where there is no data. The demo's lattice
(``clients.samples.PARIS_REGION_SPACING_M``) is read from this table (bench/RESULTS.md).
"""

from __future__ import annotations

import argparse
import datetime
import platform
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import publish, weighted_cv  # bench/ is on the path when run as a script

from bdf import ingest
from clients import samples

CANDIDATES_M = [
    np.array([4000.0, 4000.0, 1000.0]),
    np.array([2000.0, 2000.0, 1000.0]),
    np.array([2000.0, 2000.0, 500.0]),
]


def prior_ripple(spacing, gamma) -> float:
    """``1 - min / max`` of the prior std's shape ``sqrt(sum_m phi_m(x)^2)`` over a cell of
    an infinite lattice (separable: the product of the per-axis sums)."""
    t = np.linspace(0.0, 1.0, 201)[:, None]  # position in the cell, in steps
    k = np.arange(-20, 21)[None, :]
    per_axis = [
        np.exp(-2.0 * g * s**2 * (t - k) ** 2).sum(axis=1) for s, g in zip(spacing, gamma, strict=True)
    ]
    shape = np.sqrt(np.einsum("i,j,k->ijk", *per_axis))
    return float(1.0 - shape.min() / shape.max())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cutoff", type=float, default=1e-9, help="kernel cutoff of every candidate")
    ap.add_argument("--directions", type=int, default=1, help="heading sectors of every candidate")
    ap.add_argument("--gammas", default="1,2", help="gamma x spacing^2 of every lattice, comma-separated")
    ap.add_argument("--no-append", action="store_true", help="print only, do not append to RESULTS.md")
    args = ap.parse_args(argv)
    obs, lower, upper = samples.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    train = obs.subset(~test)
    lower = lower - [0, 0, 1000]  # the region's box (samples.paris_region)
    scales = [float(g) for g in args.gammas.split(",")]
    rows = weighted_cv(train, lower, upper, CANDIDATES_M, args.cutoff, scales, args.directions)
    for r in rows:
        r["ripple"] = prior_ripple(r["spacing"], r["gamma"])
    report = [
        "",
        f"## Region lattice by cross-validation, {datetime.date.today()} (issue 16)",
        "",
        f"`.venv/bin/python bench/bench_lattice.py {' '.join(sys.argv[1:] if argv is None else argv)}` "
        f"on {platform.machine()}, 2 cores, Python {platform.python_version()}. Training flights of "
        f"the flight split ({len(train.X)} points), 5 folds of whole flights, track weights per "
        f"lattice, alpha = beta = auto, cutoff {args.cutoff:g}, {args.directions} heading sector(s).",
        "",
        "| spacing m | gamma x spacing^2 | hinges | CV RMSE | CV MSLL | prior std ripple | s per candidate |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        report.append(
            f"| {r['spacing']} | {r['gamma x spacing^2']:g} | {r['hinges']} | {r['rmse']:.2f} | "
            f"{r['msll']:.3f} | {r['ripple']:.0%} | {r['s']:.0f} |"
        )
    publish(report, not args.no_append)


if __name__ == "__main__":
    main()
