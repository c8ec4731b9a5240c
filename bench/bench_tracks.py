"""Raw tracks in, a plausible calibrated map out: the Paris flight split as users send it.

The training flights' raw 1 Hz rows go to the service over HTTP with their ``track`` and
``t`` columns and nothing computed for them (no weights), in ``--chunks`` uploads cut by
time (so flights are cut across uploads); the service weighs each track's rows
(:func:`bdf.ingest.track_weights`). A new region as created (``directions: "auto"``, its
uploads split into 16 sectors until a fit chooses), 8 sectors, and one class. The map is
scored on the held-out flights (20 %, seed 0): RMSE, MSLL, cov95, for directional maps the
mixture MSLL and the conditional RMSE (the mode of the heading each held-out row flies, as
the service answers it), and over the box it is judged as traffic can fly
(:func:`plausibility`): on a 1 km grid at every 500 m of altitude, the fastest horizontal
speed of the mean and of every mode with share >= 0.05, the share of voxels above the bound
(1.1 x the 99.9th percentile of the horizontal speeds of the rows within 1 km of the
altitude, 400 m/s where none is), and the share of voxels ``known``.

``--sweep`` adds the lattices a user would plausibly choose (horizontal spacing 1, 2, 4, 8
km, ``--spacings``, x vertical 0.5 and 1 km, 1 and 8 sectors, gamma = 1 / spacing^2) with
the same rows and their track columns, through the library's own path (the one function
uploads learn through).

``--prior-reach`` instead: the 8-sector demo map (the library's path) with a mode's prior
mean (:func:`bdf.posterior._local_prior`) over each reach of hinges either side, ``layer``
the whole layer (the prior before 2026-11-28): what the reach trades; the served reach also
with its shares cut at 0 (before ``SHARE_FLOOR``).

``--additivity`` instead: the same rows as 1, 10 and 100 uploads cut by time, in shuffled
orders, through the library's own path: how far each map is from one upload's.

    python bench/bench_tracks.py [--chunks 10] [--sweep [--spacings 8,4,2,1]] [--no-http] [--publish]
    python bench/bench_tracks.py --prior-reach 2,4,8,16,layer [--publish]
    python bench/bench_tracks.py --additivity [--publish]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_core import publish, rows_table  # bench/ is on the path when run as a script
from scipy.stats import norm

from bdf import ingest, metrics, posterior
from bdf.region.evidence import accepted_increments, region_total
from bdf.region.map import (
    FASTEST_QUANTILE,
    MODE_SHARE,
    NEAR_ALTITUDE_M,
    PLAUSIBLE_FACTOR,
    RegionMap,
    compute_posterior,
)
from bdf.region.spec import RegionSpec
from clients import samples
from clients.local import LocalService
from clients.sdk import BDFClient

#: the bound's definition, the service's (:mod:`bdf.region.map`), computed here from the rows
#: themselves at each altitude exactly: an independent check of the service's histogram
FASTEST_PERCENTILE = 100 * FASTEST_QUANTILE


def split():
    obs, lower, upper = samples.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    return obs.subset(~test), obs.subset(test), lower, upper


def speed_bound(train: ingest.Observations, alts, envelope_mps: float) -> np.ndarray:
    """The plausibility bound at each altitude of ``alts`` (m/s), from the rows."""
    speed = np.hypot(train.V[:, 0], train.V[:, 1])
    out = np.full(len(alts), envelope_mps)
    for i, z in enumerate(alts):
        near = np.abs(train.X[:, 2] - z) <= NEAR_ALTITUDE_M
        if near.any():
            out[i] = PLAUSIBLE_FACTOR * np.percentile(speed[near], FASTEST_PERCENTILE)
    return out


def plausibility(spec: RegionSpec, rmap: RegionMap, train) -> dict:
    """The map over the box as traffic can fly it: a 1 km grid at every 500 m of altitude."""
    axes = [np.arange(lo + 500.0, hi, 1000.0) for lo, hi in zip(spec.lower[:2], spec.upper[:2], strict=True)]
    axes.append(np.arange(spec.lower[2] + 500.0, spec.upper[2], 500.0))
    modes = rmap.predict_grid_modes(axes)
    mean, _, known = rmap.predict_grid(axes, modes=modes)
    fastest = np.hypot(mean[..., 0], mean[..., 1])
    if not spec.one_class:
        mode_speed = np.hypot(modes.mean[..., 0], modes.mean[..., 1])
        fastest = np.maximum(fastest, np.where(modes.share >= MODE_SHARE, mode_speed, 0.0).max(axis=-1))
    bound = speed_bound(train, axes[2], spec.envelope.max_horizontal_speed_mps)[None, None, :]
    over = fastest > bound
    worst = np.unravel_index(np.argmax(fastest / bound), fastest.shape)
    return {
        "max speed [m/s]": float(fastest.max()),
        "worst ratio to bound": float((fastest / bound).max()),
        "implausible voxels": float(over.mean()),
        "known": float(known.mean()),
        "implausible among known": float(over[known].mean()) if known.any() else 0.0,
        "worst voxel": worst_voxel(
            spec, [a[i] for a, i in zip(axes, worst, strict=True)], mean[worst], modes, worst, train
        ),
    }


def worst_voxel(spec: RegionSpec, at, mean, modes, index, train) -> str:
    """Where the map is furthest above the bound, what flies there, and the rows of that
    class within 3 km horizontally and 700 m vertically: what the map answers it from."""
    speeds = np.hypot(modes.mean[index][:, 0], modes.mean[index][:, 1])
    speeds = np.where(modes.share[index] >= MODE_SHARE, speeds, 0.0)
    c = int(np.argmax(speeds))
    text = f"({at[0] / 1e3:.1f}, {at[1] / 1e3:.1f}) km at {at[2]:.0f} m: "
    if speeds[c] <= np.hypot(mean[0], mean[1]):
        return text + f"the mean, {np.hypot(mean[0], mean[1]):.0f} m/s"
    near = (np.abs(train.X[:, :2] - at[:2]).max(axis=1) < 3000) & (np.abs(train.X[:, 2] - at[2]) < 700)
    near &= spec.sectors.classify(train.V) == c
    row_speed = np.hypot(train.V[near, 0], train.V[near, 1])
    text += (
        f"the mode of class {c} ({speeds[c]:.0f} m/s, share {modes.share[index][c]:.2f}, "
        f"data weight {modes.weight[index][c]:.1f}); its {near.sum()} rows near: "
    )
    if not near.any():
        return text + "none"
    z = train.X[near, 2]
    return text + f"{row_speed.min():.0f}-{row_speed.max():.0f} m/s at {z.min():.0f}-{z.max():.0f} m"


def held_out(spec: RegionSpec, rmap: RegionMap, train, test) -> dict:
    modes = rmap.predict_modes(test.X)
    mean, std, known = rmap.predict(test.X, modes=modes)
    row = {
        "RMSE": float(metrics.rmse(test.V, mean)),
        "MSLL": float(metrics.msll(test.V, mean, std, train.V.mean(0), train.V.std(0))),
        "cov95": float(metrics.coverage(test.V, mean, std)),
        "cov95 known": float(metrics.coverage(test.V[known], mean[known], std[known]))
        if known.any()
        else np.nan,
        "known held-out": float(known.mean()),
        # what the map itself expects of that interval: its model's mixture of modes (one
        # Gaussian: 0.95; a mixture's moments cover more where its modes are far apart)
        "cov95 known, expected": expected_coverage(
            rmap.posterior.predict_modes(spec.inside_points(test.X[known])), mean[known], std[known]
        ),
    }
    if not spec.one_class:
        row["mixture MSLL"] = metrics.mixture_msll(
            test.V, modes.share, modes.mean, modes.std, train.V.mean(0), train.V.std(0)
        )
        # the service's answer at the heading each held-out row flies (the slow class's below it)
        flown, flown_std = modes.flown(spec.sectors, test.V)
        row["cond. RMSE"] = float(metrics.rmse(test.V, flown))
        row["cond. cov95"] = float(metrics.coverage(test.V, flown, flown_std))
    return row


def expected_coverage(modes, mean, std) -> float:
    """The probability the map's own mixture of modes (share, mean, std per class) gives to
    ``mean -/+ 1.96 std`` of each component, averaged: what cov95 of that answer is if the
    map is calibrated."""
    half = norm.ppf(0.975) * std[:, None, :]
    inside = norm.cdf((mean[:, None, :] + half - modes.mean) / modes.std) - norm.cdf(
        (mean[:, None, :] - half - modes.mean) / modes.std
    )
    return float(np.mean(np.einsum("nc,ncd->nd", modes.share, inside)))


def library_increments(spec: RegionSpec, train, tracks: bool) -> dict:
    """The tile increments of the rows through the library's own path (what uploads store)."""
    kw = {"track": train.flight, "time": train.time} if tracks else {}
    return accepted_increments(spec, train.X, train.V, **kw)[0]


def library_map(spec: RegionSpec, train, tracks: bool, increments: dict | None = None) -> RegionMap:
    """The map of the rows (or of their ``increments``, :func:`library_increments`) through
    the library's own path (no tiles kept, no HTTP)."""
    if increments is None:
        increments = library_increments(spec, train, tracks)
    evidence = region_total(spec, {k: i.evidence for k, i in increments.items()})
    return RegionMap(spec, compute_posterior(spec, evidence))


def http_map(spec: RegionSpec, train, chunks: int, tmp: Path) -> tuple[RegionMap, dict]:
    """The map the service builds from the raw rows in ``chunks`` uploads cut by time."""
    order = np.argsort(train.time, kind="stable")
    parts = np.array_split(order, chunks)
    with LocalService(tmp / "data", log_path=tmp / "service.log") as svc, BDFClient(svc.url) as bdf:
        bdf.create_region(spec)
        t0 = time.perf_counter()
        untracked = 0
        for i, rows in enumerate(parts):
            result = bdf.upload(
                spec.name,
                train.X[rows],
                train.V[rows],
                track=train.flight[rows],
                t=train.time[rows],
                key=f"c{i}",
            )
            untracked += result.untracked
        upload_s = time.perf_counter() - t0
        view = bdf.fit_hyperparameters(spec.name)  # the settled map
        settled_s = time.perf_counter() - t0
    # the same store, read back through the library: the map the service answers from
    from service.store import open_store

    store = open_store(f"sqlite:///{tmp / 'data'}")
    try:
        from service.maps import RegionMaps

        state = RegionMaps(store, cache_mb=4096).refresh(spec.name)
        rmap = RegionMap(spec, state.posterior)
    finally:
        store.close()
    extra = {
        "view: worst ratio": view.plausibility["worst_ratio"],
        "view: at bound": str(view.hyperparameters["at_bound"]),
        "uploads [s]": upload_s,
        "settled [s]": settled_s,
        "untracked": untracked,
    }
    return rmap, extra


def additivity(train, test, lower, upper, counts=(10, 100)) -> list[dict]:
    """The same raw rows as 1, 10 and 100 uploads cut by time (flights cut across them),
    summed in a shuffled order through the function uploads learn through: the largest
    difference of the held-out answers from one upload's (mean over the climatology std,
    std relative)."""
    rows = []
    climate = train.V.std(axis=0)
    order = np.argsort(train.time, kind="stable")
    for directions in (1, 8):
        spec = samples.paris_demo_region(lower, upper, directions=directions)
        answers = {}
        for count in (1, *counts):
            chunks = np.array_split(order, count)
            total = {}
            for k in np.random.default_rng(count).permutation(count):
                part = chunks[k]
                kw = {"track": train.flight[part], "time": train.time[part]}
                increments, _ = accepted_increments(spec, train.X[part], train.V[part], **kw)
                for key, inc in increments.items():
                    total[key] = inc.evidence if key not in total else total[key] + inc.evidence
            rmap = RegionMap(spec, compute_posterior(spec, region_total(spec, total)))
            answers[count] = rmap.predict(test.X)[:2]
        for count in counts:
            (mean, std), (mean1, std1) = answers[count], answers[1]
            rows.append(
                {
                    "sectors": directions,
                    "uploads": count,
                    "max |mean - one upload's| / climatology std": float(
                        (np.abs(mean - mean1) / climate).max()
                    ),
                    "max |std / one upload's - 1|": float(np.abs(std / std1 - 1).max()),
                }
            )
            print(rows[-1], flush=True)
    return rows


def sweep(train, test, lower, upper, spacings_km=(8.0, 4.0, 2.0, 1.0)) -> list[dict]:
    """The map of the raw rows with their track columns on each lattice of the sweep,
    coarsest first, through the library's own path: 8 sectors, and one class as a region
    answers it (the same evidence and posterior, answered as the mixture's moments)."""
    rows = []
    for h in (1e3 * km for km in spacings_km):
        for v in (1000.0, 500.0):
            spacing = np.array([h, h, v])
            lattice = f"{h / 1e3:g} x {h / 1e3:g} x {v / 1e3:g}"
            t0 = time.perf_counter()
            specs = [
                samples.paris_region(lower, upper, spacing, 1 / spacing**2, directions=d) for d in (1, 8)
            ]
            try:
                rmap = library_map(specs[1], train, True)
            except ValueError as exc:  # a lattice the library refuses
                rows.append({"spacing [km]": lattice, "error": " ".join(str(exc).split())[:160]})
                continue
            build_s = time.perf_counter() - t0
            for spec in specs:
                answered = RegionMap(spec, rmap.posterior)
                row = {
                    "spacing [km]": lattice,
                    "sectors": spec.directions,
                    "model": spec.model_directions,
                    **held_out(spec, answered, train, test),
                    **plausibility(spec, answered, train),
                    "build [s]": build_s,
                }
                rows.append(row)
                print(row, flush=True)
    return rows


def prior_reach(train, test, lower, upper, reaches: list[str]) -> list[dict]:
    """The 8-sector demo map with a mode's prior mean over each reach (hinges either side,
    or ``layer``: every hinge of the layer); and the served reach's map with its shares cut
    at 0 instead of raised to :data:`bdf.posterior.SHARE_FLOOR` (the rule before it)."""
    rows, kept = [], (posterior.LOCAL_PRIOR_HINGES, posterior.SHARE_FLOOR)
    spec = samples.paris_demo_region(lower, upper, directions=8)

    def judged(rmap, **label) -> None:
        rows.append({**label, **held_out(spec, rmap, train, test), **plausibility(spec, rmap, train)})
        print(rows[-1], flush=True)

    try:
        for reach in reaches:
            posterior.LOCAL_PRIOR_HINGES = max(spec.grid.shape) if reach == "layer" else int(reach)
            rmap = library_map(spec, train, True)
            judged(rmap, **{"reach [hinges]": reach, "share floor": kept[1]})
            if posterior.LOCAL_PRIOR_HINGES == kept[0]:
                posterior.SHARE_FLOOR = 0.0  # shares are made at query time: the same map
                judged(rmap, **{"reach [hinges]": reach, "share floor": 0.0})
                posterior.SHARE_FLOOR = kept[1]
    finally:
        posterior.LOCAL_PRIOR_HINGES, posterior.SHARE_FLOOR = kept
    return rows


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--chunks", type=int, default=10)
    parser.add_argument("--sweep", action="store_true")
    parser.add_argument(
        "--spacings", default="8,4,2,1", help="the sweep's horizontal spacings (km, comma-separated)"
    )
    parser.add_argument(
        "--additivity", action="store_true", help="only: 1, 10 and 100 uploads, the library's path"
    )
    parser.add_argument(
        "--prior-reach", help="only: the 8-sector demo map at each reach of a mode's prior (e.g. 2,4,layer)"
    )
    parser.add_argument("--no-http", action="store_true", help="the library's path only")
    parser.add_argument("--publish", action="store_true", help="append the report to bench/RESULTS.md")
    args = parser.parse_args()
    train, test, lower, upper = split()
    if args.prior_reach:
        command = f"python bench/bench_tracks.py --prior-reach {args.prior_reach}"
        lines = [
            "Paris flight split, raw rows with track and t, demo lattice, 8 sectors (library path), "
            "by the reach of a mode's prior mean:",
            rows_table(prior_reach(train, test, lower, upper, args.prior_reach.split(","))),
        ]
        publish([f"\n## A mode's prior ({time.strftime('%Y-%m-%d')}, `{command}`)\n", *lines], args.publish)
        return
    if args.additivity:
        lines = ["Paris flight split, raw rows with track and t, demo lattice, 1 and 8 sectors:"]
        lines.append(rows_table(additivity(train, test, lower, upper)))
        command = "python bench/bench_tracks.py --additivity"
        publish(
            [f"\n## Tracks cut across uploads ({time.strftime('%Y-%m-%d')}, `{command}`)\n", *lines],
            args.publish,
        )
        return
    lines = [
        f"Paris flight split: {len(train)} training rows of {len(np.unique(train.flight))} flights "
        f"(raw 1 Hz, track and t columns, no weights), {len(test)} held-out rows; demo lattice "
        "2 x 2 x 1 km."
    ]
    rows = []
    # a new region as created (directions "auto": its uploads split into 16 sectors until a
    # fit chooses); 8 sectors; one class as a region answers it (the moments of its model's
    # mixture); and one class on the paper's model of one field
    for directions, model in (("auto", None), (8, 8), (1, None), (1, 1)):
        spec = samples.paris_demo_region(lower, upper, directions=directions, model_directions=model)
        if args.no_http:
            rmap, extra = library_map(spec, train, True), {}
            how = "library"
        else:
            with tempfile.TemporaryDirectory() as tmp:
                rmap, extra = http_map(spec, train, args.chunks, Path(tmp))
            how = f"HTTP, {args.chunks} uploads"
        row = {
            "sectors": directions,
            "model": spec.model_directions,
            "built by": how,
            **held_out(spec, rmap, train, test),
            **plausibility(spec, rmap, train),
            **extra,
        }
        print(row, flush=True)
        rows.append(row)
        if model == 1:
            continue  # its rows without track columns: the table
        # side by side: the same rows as sent without their track columns (independent)
        raw = library_map(spec, train, False)
        row = {
            "sectors": directions,
            "model": spec.model_directions,
            "built by": "library, no track columns",
            **held_out(spec, raw, train, test),
            **plausibility(spec, raw, train),
        }
        print(row, flush=True)
        rows.append(row)
    lines.append(rows_table(rows))
    if args.sweep:
        lines += ["", "Sweep (the library's path, raw rows with their track columns):"]
        spacings = [float(km) for km in args.spacings.split(",")]
        lines.append(rows_table(sweep(train, test, lower, upper, spacings)))
    command = "python bench/bench_tracks.py" + (" --no-http" if args.no_http else "")
    command += f" --sweep --spacings {args.spacings}" if args.sweep else ""
    publish([f"\n## Raw tracks in ({time.strftime('%Y-%m-%d')}, `{command}`)\n", *lines], append=args.publish)


if __name__ == "__main__":
    main()
