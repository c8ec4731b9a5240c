"""City-scale builds: throughput, memory and accuracy against a known field.

    python bench/bench_build.py                       # 1, 5 and 20 million points
    python bench/bench_build.py --points 1e6 --directions 8

For each size N, ``make_city`` writes the synthetic city (cached under ``--data``), then:

* serial: every slice's evidence in this process, one after the other (no Dask);
* Dask with 1 and 2 worker processes (:func:`service.build.local_cluster`, as ``bdf build``
  starts them: one thread each, ``--worker-memory`` per worker), building into a fresh
  SQLite store: points per second for the evidence, the time to commit (the region's
  posterior, then the transaction) and each worker's peak RSS, sampled every 20 ms;
* the built map against the city's known field on held-out traffic: RMSE of the mean
  against the true mean velocity, 95 % coverage of the predictive std, and with
  directions the RMSE of the mode of each point's true heading against its lane's velocity.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil
from distributed import Client

sys.path.insert(0, str(Path(__file__).resolve().parent))
import make_city

from bdf.region.evidence import increments
from bdf.region.spec import RegionSpec
from service.build import BATCH_ROWS, build, local_cluster, merge, plan, slice_evidence
from service.maps import RegionMaps
from service.store import open_store


class PeakRSS:
    """The largest resident set of each of some processes, sampled in a thread."""

    def __init__(self, pids, every_s: float = 0.02):
        self.procs = [psutil.Process(p) for p in pids]
        self.peak = [0] * len(self.procs)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(every_s,), daemon=True)

    def _run(self, every_s):
        while not self._stop.is_set():
            for i, proc in enumerate(self.procs):
                try:
                    self.peak[i] = max(self.peak[i], proc.memory_info().rss)
                except psutil.NoSuchProcess:
                    pass
            time.sleep(every_s)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def city(data: Path, points: int, one_file: bool) -> list[Path]:
    folder = data / f"city-{points}{'-one-file' * one_file}"
    files = sorted(folder.glob("*.parquet"))
    if files and (folder / "done").exists():
        return files
    files = make_city.write(folder, points, rows_per_file=None if one_file else make_city.ROWS_PER_FILE)
    (folder / "done").touch()
    return files


def serial(spec: RegionSpec, files, batch_rows: int) -> tuple[float, int, int]:
    """Seconds, points and peak RSS growth of the evidence in this process."""
    spec_json = spec.model_dump_json()
    base = psutil.Process().memory_info().rss
    with PeakRSS([os.getpid()]) as rss:
        start = time.perf_counter()
        total = None
        for piece in plan(files):
            part = slice_evidence(spec_json, piece, batch_rows)
            total = part if total is None else merge(total, part)
        seconds = time.perf_counter() - start
    return seconds, total.summary["accepted"], rss.peak[0] - base


def dask_build(spec: RegionSpec, files, workers: int, memory: str, batch_rows: int, store_url: str):
    store = open_store(store_url)
    store.create_region(spec)
    with local_cluster(workers, memory) as cluster, Client(cluster) as client:
        client.run(_warm, spec.model_dump_json())  # compile the kernels before the clock starts
        with PeakRSS(client.run(os.getpid).values()) as rss:
            start = time.perf_counter()
            result = build(store, spec.name, files, client, progress=False, batch_rows=batch_rows)
            seconds = time.perf_counter() - start
    return store, result, seconds, rss.peak


def _warm(spec_json: str) -> None:
    """Compile (or load) every kernel a slice uses: points spread over the region, so
    tiles sort their points into blocks, as the city's do."""
    spec = RegionSpec.model_validate_json(spec_json)
    X, V, _ = make_city.sample(20_000, np.random.default_rng(1))
    inside = spec.inside(X)
    increments(spec, X[inside], V[inside])


def score(store, spec: RegionSpec, seed: int = 99, n: int = 50_000) -> dict:
    """The built map against the city's known field at held-out traffic."""
    X, V, lane = make_city.sample(n, np.random.default_rng(seed))
    maps = RegionMaps(store)
    try:
        pred = maps.predict(spec.name, X)
        truth, _ = make_city.true_mean(X)
        out = {
            "rmse_mean": float(np.sqrt(np.mean((pred.mean - truth) ** 2))),
            "rmse_climatology": float(np.sqrt(np.mean((truth - V.mean(axis=0)) ** 2))),
            "coverage": float(np.mean(np.abs(V - pred.mean) <= 1.96 * pred.std)),
        }
        if not spec.one_class:
            velocity = np.array([make_city.lane_velocity(lane) for lane in make_city.LANES])[lane]
            heading = np.degrees(np.arctan2(velocity[:, 0], velocity[:, 1])) % 360
            cond = maps.predict(spec.name, X, heading_deg=heading)
            out["rmse_mode"] = float(np.sqrt(np.mean((cond.mean - velocity) ** 2)))
            out["coverage_mode"] = float(np.mean(np.abs(V - cond.mean) <= 1.96 * cond.std))
        return out
    finally:
        maps.close()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=float, nargs="+", default=[1e6, 5e6, 20e6])
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--directions", type=int, default=1)
    parser.add_argument("--worker-memory", default="1GB")
    parser.add_argument("--batch-rows", type=int, default=BATCH_ROWS)
    parser.add_argument("--serial", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--one-file", action="store_true", help="each city in one Parquet file")
    parser.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "bdf-bench-city")
    args = parser.parse_args(argv)
    spec = RegionSpec.model_validate(make_city.region_spec(directions=args.directions))
    command = " ".join(["python bench/bench_build.py", *(argv or sys.argv[1:])])
    print(
        f"## Builds, {time.strftime('%Y-%m-%d')}\n\n`{command}`"
        f" on {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}. "
        f"City: {spec.grid.size} hinges ({' x '.join(map(str, spec.grid.shape))}), "
        f"{int(np.prod(spec.tile_counts))} tiles, directions {spec.directions}, cutoff {spec.cutoff:g}; "
        f"batch {args.batch_rows:,} rows; worker memory limit {args.worker_memory}; "
        f"{'one Parquet file' if args.one_file else 'files of 1M rows'}, row groups of 100k.\n"
    )
    print(
        "| N | path | evidence s | Mpts/s | per worker Mpts/s | commit s | peak RSS MB (per worker) | "
        "RMSE mean | RMSE climatology | cov95 |"
        + (" RMSE mode | cov95 mode |" if args.directions > 1 else "")
    )
    print("|" + "---|" * (10 + 2 * (args.directions > 1)))
    for points in map(int, args.points):
        files = city(args.data, points, args.one_file)
        if args.serial:
            seconds, n, grown = serial(spec, files, args.batch_rows)
            print(
                f"| {n:,} | serial | {seconds:.1f} | {n / seconds / 1e6:.3f} | {n / seconds / 1e6:.3f} | - | "
                f"+{grown / 2**20:.0f} | - | - | - |" + (" - | - |" if args.directions > 1 else ""),
                flush=True,
            )
        for workers in args.workers:
            with tempfile.TemporaryDirectory() as tmp:
                store, result, seconds, peaks = dask_build(
                    spec, files, workers, args.worker_memory, args.batch_rows, f"sqlite:///{tmp}/data"
                )
                n, ev, commit = result["accepted"], result["seconds"]["evidence"], result["seconds"]["commit"]
                s = score(store, spec)
                store.close()
            extra = f" {s['rmse_mode']:.2f} | {s['coverage_mode']:.3f} |" if args.directions > 1 else ""
            peak_mb = ", ".join(f"{p / 2**20:.0f}" for p in peaks)
            print(
                f"| {n:,} | Dask, {workers} worker{'s' * (workers > 1)} | {ev:.1f} | {n / ev / 1e6:.3f} | "
                f"{n / ev / 1e6 / workers:.3f} | {commit:.1f} | {peak_mb} | "
                f"{s['rmse_mean']:.2f} | {s['rmse_climatology']:.2f} | {s['coverage']:.3f} |{extra}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
