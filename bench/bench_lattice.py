"""The demo region's lattice: flight-grouped cross-validation of hinge spacings and kernels.

    .venv/bin/python bench/bench_lattice.py [--cutoff 1e-9] [--no-append]

Candidates: 2 km horizontally (the finest the region must reach) by 500 m and 1 km
vertically, each with gamma = 1 or 2 times 1 / spacing^2, and today's 4 km core lattice as
the reference. Data: the training flights of the core benchmark's flight split (20 % of
whole flights held out, seed 0); 5 folds of whole flights; track weights per lattice
(each flight weighs 1 per lattice cell it crosses); alpha = beta = auto, one class. The
lattice with the best CV MSLL among the 2 km ones becomes ``bdf.ingest.PARIS_REGION_SPACING_M``
(and its gamma scale), which the demo's region uses.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import publish  # bench/ is on the path when run as a script

from bdf import crossval, ingest

CANDIDATES_M = [
    np.array([4000.0, 4000.0, 1000.0]),
    np.array([2000.0, 2000.0, 1000.0]),
    np.array([2000.0, 2000.0, 500.0]),
]
GAMMA_SCALES = (1.0, 2.0)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cutoff", type=float, default=1e-9, help="kernel cutoff of every candidate")
    ap.add_argument("--no-append", action="store_true", help="print only, do not append to RESULTS.md")
    args = ap.parse_args(argv)
    obs, lower, upper = ingest.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    train = obs.subset(~test)
    lower = lower - [0, 0, 1000]  # the region's box (ingest.paris_region)
    rows = []
    for spacing in CANDIDATES_M:
        weight = ingest.track_weights(train, spacing)
        for scale in GAMMA_SCALES:
            t0 = time.perf_counter()
            _, (row,) = crossval.cross_validate(
                train.X,
                train.V,
                lower,
                upper,
                [(spacing, scale / spacing**2)],
                groups=train.flight,
                sample_weight=weight,
                cutoff=args.cutoff,
            )
            rows.append({**row, "scale": scale, "s": time.perf_counter() - t0})
            print(rows[-1], flush=True)
    fine = [r for r in rows if r["spacing"][0] <= 2000.0]
    best = min(fine, key=lambda r: r["msll"])
    report = [
        "",
        f"## Region lattice by cross-validation, {datetime.date.today()} (issue 16)",
        "",
        f"`.venv/bin/python bench/bench_lattice.py {' '.join(sys.argv[1:] if argv is None else argv)}` "
        f"on {platform.machine()}, 2 cores, Python {platform.python_version()}. Training flights of "
        f"the flight split ({len(train.X)} points), 5 folds of whole flights, track weights per "
        f"lattice, alpha = beta = auto, cutoff {args.cutoff:g}.",
        "",
        "| spacing m | gamma x spacing^2 | hinges | CV RMSE | CV MSLL | s (5 folds) |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        mark = " **(picked)**" if r is best else ""
        report.append(
            f"| {r['spacing']}{mark} | {r['scale']:g} | {r['hinges']} | {r['rmse']:.2f} | "
            f"{r['msll']:.3f} | {r['s']:.0f} |"
        )
    publish(report, not args.no_append)


if __name__ == "__main__":
    main()
