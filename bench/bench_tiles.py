"""Region maps on real ADS-B traffic around Paris: one field stored in tiles, served exactly.

    .venv/bin/python bench/bench_tiles.py [--spacing 4000,4000,1000 ...] [--cutoff 1e-12]
        [--cutoffs 1e-6,1e-8,1e-10] [--directions 8] [--no-append]

Region: the demo's (`clients.samples.paris_region`: the core benchmark's 80 km x 80 km box,
10 km tiles over the whole altitude band, gamma = 1/spacing^2). Training data: the flight
split of the core benchmark (20 % of whole flights held out, seed 0), track-weighted.
Everything runs in process through `RegionMaps` on SQLite in a temporary directory.

Per lattice: the fit (increments, the evidence maximum of the whole region, one
transaction), a refresh after a 1,000-row upload (the posterior of the new version, its
"auto" found again from the previous optimum), a cold 10,000-point query (fresh caches,
the stencil's too: its pattern, ordering and symbolic analysis, then the posterior from
the stored evidence, as in a new process) and a warm one; the factorisation's
multiply-adds against this machine's measured dense GEMM rate, the dense Cholesky's (M^3
/ 6) at that rate, and CHOLMOD's of the same matrix in the same order; a support's first
factorisation (with its symbolic analysis and the layout of its blocks); the factor's
work in our nested-dissection order against CHOLMOD's METIS order (and METIS's time);
held-out accuracy of the served map and of one `BayesianDynamicField` over the region's
lattice (largest difference of the means); plausibility on the 500 m grid at 500-5,500 m
(largest horizontal mean speed over the fastest observed in its 1 km band, and the voxels
above it; with ``--directions``, the same for every mode with at least 5 % of the
traffic; largest std over the climatology std, the root mean square of the training
velocities per component); seam ratios: the mean absolute step between neighbouring 500 m
cells that straddle a tile border, over the same between cells that do not (1.0: borders
invisible).

With ``--cutoffs``: the error of a looser kernel cutoff (the precision's stencil) on the
first lattice, against the default 1e-12 at the same hyperparameters, with the cost of
its factorisation and selected inversion.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import accuracy, publish  # bench/ is on the path when run as a script
from sksparse.cholmod import analyze

from bdf import ingest, sparse
from bdf.kernel import DEFAULT_CUTOFF
from bdf.region.evidence import region_total
from bdf.region.map import region_field
from bdf.region.spec import RegionSpec
from clients import samples
from service.maps import RegionMaps
from service.store import open_store


def gemm_rate() -> float:
    """Multiply-adds per second of a 2,000 x 2,000 float64 GEMM (best of 3)."""
    a = np.random.default_rng(0).standard_normal((2000, 2000))
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        a @ a
        best = min(best, time.perf_counter() - t0)
    return 2000**3 / best


def seam_ratio(values: np.ndarray, axes, spec) -> float:
    """Mean |step| between x- or y-neighbours across a tile border, over the same elsewhere."""
    steps, border = [], []
    for d in (0, 1):
        step = np.abs(np.diff(values, axis=d)).max(axis=-1)  # largest component step
        tile = np.floor((axes[d] - spec.lower[d]) / spec.tile_size_m[d])
        crosses = np.diff(tile) != 0
        shape = [1, 1, 1]
        shape[d] = -1
        steps.append(step.ravel())
        border.append(np.broadcast_to(crosses.reshape(shape), step.shape).ravel())
    steps, border = np.concatenate(steps), np.concatenate(border)
    return float(steps[border].mean() / steps[~border].mean())


def paris(spacing, cutoff, directions=1) -> RegionSpec:
    _, lower, upper = samples.load_paris()
    return samples.paris_region(lower, upper, spacing, directions=directions, cutoff=cutoff)


def cutoff_errors(spacing, cutoffs, obs, test) -> list[str]:
    """Largest error of the map at each cutoff against 1e-12 on 20,000 random points."""
    train = obs.subset(~test)
    exact = paris(spacing, DEFAULT_CUTOFF)
    weight = train.track_weights(exact.gamma)
    climate = np.sqrt(np.average(train.V**2, axis=0, weights=weight))
    ref = region_field(exact).fit(train.X, train.V, sample_weight=weight)
    Q = np.random.default_rng(1).uniform(exact.lower, exact.upper, (20_000, 3))
    ref_mean, ref_std = ref.predict(Q, return_std=True)
    lines = [
        f"Error against cutoff 1e-12 ({exact.grid.size} hinges, alpha, beta fitted at 1e-12):",
        "",
        "| cutoff | stencil offsets (half) | factor Gmadd | factor [s] | selected inversion [s] "
        "| max mean error / climatology std | max std relative error |",
        "|---|---|---|---|---|---|---|",
    ]
    for cutoff in [*cutoffs, DEFAULT_CUTOFF]:
        spec = paris(spacing, cutoff)
        field = region_field(spec, ref.alpha_, ref.beta_).fit(train.X, train.V, sample_weight=weight)
        mean, std = field.predict(Q, return_std=True)
        stencil = sparse.stencil_on(spec.grid, spec.kernel)
        band = field.evidence_.total().gram_band(stencil)
        t0 = time.perf_counter()
        factor = stencil.factor_of(band, float(np.mean(ref.alpha_) / np.mean(ref.beta_)))
        t1 = time.perf_counter()
        factor.inverse_band()
        t2 = time.perf_counter()
        lines.append(
            f"| {cutoff:g} | {len(stencil.offsets)} | {factor.madds / 1e9:.1f} | {t1 - t0:.2f} "
            f"| {t2 - t1:.2f} | {(np.abs(mean - ref_mean) / climate).max():.2e} "
            f"| {(np.abs(std - ref_std) / ref_std).max():.2e} |"
        )
    return lines


def run(spacing, cutoff, obs, test, rate, directions=1) -> dict:
    spec = paris(spacing, cutoff, directions)
    train = obs.subset(~test)
    weight = train.track_weights(spec.gamma)
    row = {"hinges": spec.grid.size, "stencil": len(sparse.stencil_on(spec.grid, spec.kernel).offsets)}
    with tempfile.TemporaryDirectory() as tmp:
        store = open_store(f"sqlite:///{tmp}")
        store.create_region(spec)
        maps = RegionMaps(store)
        t0 = time.perf_counter()
        maps.upload(spec.name, "fit", train.X, train.V, sample_weight=weight, replace=True)
        row["fit [s]"] = time.perf_counter() - t0
        info = store.region(spec.name)
        alpha, beta = info.hyperparameters()
        pred = maps.predict(spec.name, obs.X[test])
        row |= {f"served {k}": v for k, v in accuracy(obs.V[test], train.V, pred.mean, pred.std).items()}
        field = region_field(spec, alpha, beta).fit(train.X, train.V, sample_weight=weight)
        mean, std = field.predict(obs.X[test], return_std=True)
        row |= {f"field {k}": v for k, v in accuracy(obs.V[test], train.V, mean, std).items()}
        row["largest mean difference, served vs field [m/s]"] = float(np.abs(pred.mean - mean).max())
        # plausibility and seams on the 500 m grid at 500-5,500 m
        axes = [np.arange(spec.lower[d], spec.upper[d] + 1, 500.0) for d in (0, 1)]
        axes.append(np.arange(500.0, 5501.0, 500.0))
        grid = maps.predict_grid(spec.name, axes, modes=not spec.one_class)
        speed = np.hypot(grid.mean[..., 0], grid.mean[..., 1])
        observed = np.hypot(train.V[:, 0], train.V[:, 1])
        band = np.floor(train.X[:, 2] / 1000.0)
        limit = np.array([observed[band == np.floor(z / 1000.0)].max() for z in axes[2]])
        climate = np.sqrt(np.average(train.V**2, axis=0, weights=weight))
        ratio = speed / limit
        row["max speed / fastest in band"] = float(ratio.max())
        row["voxels above 1.0x the fastest [%]"] = 100 * float((ratio > 1.0).mean())
        if not spec.one_class:  # every mode with at least 5 % of the traffic
            m = grid.modes
            mode_ratio = np.hypot(m.mean[..., 0], m.mean[..., 1]) / limit[None, None, :, None]
            mode_ratio = np.where(m.share > 0.05, mode_ratio, 0.0).max(axis=-1)
            row["max mode speed / fastest in band"] = float(mode_ratio.max())
            row["voxels with a mode above 1.1x the fastest [%]"] = 100 * float((mode_ratio > 1.1).mean())
        row["max std / climatology std"] = float((grid.std / climate).max())
        row["seam ratio std"] = seam_ratio(grid.std, axes, spec)
        row["seam ratio mean"] = seam_ratio(grid.mean, axes, spec)
        # a 1,000-row upload, then the refresh of its version
        t0 = time.perf_counter()
        result = maps.upload(spec.name, "more", obs.X[test][:1000], obs.V[test][:1000])
        maps.refresh(spec.name)
        row["upload 1k + refresh [s]"] = time.perf_counter() - t0
        # cold and warm 10,000-point queries
        Q = np.random.default_rng(1).uniform(spec.lower, spec.upper, (10_000, 3))
        cold = RegionMaps(store)
        sparse.lattice_stencil.cache_clear()
        t0 = time.perf_counter()
        assert cold.predict(spec.name, Q).version == result["region_version"]
        row["cold 10k query [s]"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        cold.predict(spec.name, Q)
        row["warm 10k query [ms]"] = 1e3 * (time.perf_counter() - t0)
        # the factorisation against the hardware
        ev = region_total(spec, store.snapshot(spec.name).evidence)
        st = sparse.stencil_on(spec.grid, spec.kernel)
        band_ = ev.total().gram_band(st)  # the map with one class (a directional map has one per class)
        t0 = time.perf_counter()
        shift = float(np.mean(alpha) / np.mean(beta))
        factor = st.factor_of(band_, shift)
        row["factor [s]"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        factor.inverse_band()
        row["selected inversion [s]"] = time.perf_counter() - t0
        A = factor.support.matrix(band_)  # the same factorisation by CHOLMOD, side by side
        symbolic = analyze(A, mode="supernodal", ordering_method="natural")  # not timed, as ours
        t0 = time.perf_counter()
        symbolic.cholesky(A, beta=shift)
        row["CHOLMOD factor, same order [s]"] = time.perf_counter() - t0
        madds = factor.madds
        row["factor Gmadd"] = madds / 1e9
        row["factor at GEMM rate [s]"] = madds / rate
        row["selected inversion Gmadd"] = factor.inverse_madds / 1e9
        row["selected inversion at GEMM rate [s]"] = factor.inverse_madds / rate
        row["dense Cholesky at GEMM rate [s]"] = spec.grid.size**3 / 6 / rate
        # the symbolic analysis from scratch: our order, then METIS's (CHOLMOD's own choice)
        sparse.lattice_stencil.cache_clear()
        fresh = sparse.stencil_on(spec.grid, spec.kernel)
        t0 = time.perf_counter()
        support = fresh.support(band_[0] != 0)  # the order, the pattern
        row["order and pattern [s]"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        support.factor_of(band_, shift)  # the symbolic analysis, the layout, a factorisation
        row["analysis, layout and first factorisation [s]"] = time.perf_counter() - t0
        A = support.matrix(band_)
        row["hinges the data touch [%]"] = 100 * float(support.active.mean())
        t0 = time.perf_counter()
        metis = analyze(A, mode="supernodal", ordering_method="metis")
        row["METIS analysis [s]"] = time.perf_counter() - t0
        row["METIS factor Gmadd"] = (
            sparse.stencil.factor_madds(np.diff(metis.cholesky(A, beta=shift).L().tocsc().indptr)) / 1e9
        )
        store.close()
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacing", nargs="+", default=["4000,4000,1000"], help="hinge spacings, x,y,z metres")
    ap.add_argument("--cutoff", type=float, default=DEFAULT_CUTOFF, help="the regions' kernel cutoff")
    ap.add_argument(
        "--cutoffs", default="", help="looser cutoffs to compare on the first lattice, comma-separated"
    )
    ap.add_argument("--directions", type=int, default=1, help="heading sectors of the regions")
    ap.add_argument("--no-append", action="store_true", help="print only, do not append to RESULTS.md")
    args = ap.parse_args(argv)
    obs, _, _ = samples.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    rate = gemm_rate()
    spacings = [np.array([float(v) for v in s.split(",")]) for s in args.spacing]
    rows = {
        s: run(spacing, args.cutoff, obs, test, rate, args.directions)
        for s, spacing in zip(args.spacing, spacings, strict=True)
    }
    keys = list(next(iter(rows.values())))
    report = [
        "",
        f"## bench_tiles: one region-wide field stored in tiles ({datetime.date.today()}, "
        f"{platform.machine()}, {platform.python_version()}, dense GEMM {rate / 1e9:.1f} Gmadd/s)",
        "",
        f"`.venv/bin/python bench/bench_tiles.py {' '.join(sys.argv[1:] if argv is None else argv)}`",
        "",
        f"Kernel cutoff {args.cutoff:g}, {args.directions} heading sector(s).",
        "",
        "| | " + " | ".join(f"spacing {s} m" for s in rows) + " |",
        "|---|" + "---|" * len(rows),
    ]
    for k in keys:
        cells = [f"{r[k]:.4g}" if isinstance(r[k], float) else str(r[k]) for r in rows.values()]
        report.append(f"| {k} | " + " | ".join(cells) + " |")
    if args.cutoffs:
        cutoffs = [float(c) for c in args.cutoffs.split(",")]
        report += ["", *cutoff_errors(spacings[0], cutoffs, obs, test)]
    publish(report, not args.no_append)


if __name__ == "__main__":
    main()
