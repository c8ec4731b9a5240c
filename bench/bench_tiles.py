"""Tiled maps on real ADS-B traffic around Paris: build, uploads, queries, accuracy, on SQLite and PostgreSQL.

    .venv/bin/python bench/bench_tiles.py [--postgres URL] [--uploads 50] [--no-append]

Region: the core benchmark's box (80 km x 80 km x 6 km around the Paris sample's mean
position), tiles of 10 km x 10 km x the full altitude band, 1 km overlap, on two hinge
grids: the core benchmark's (spacing 4000/4000/1000 m) and a finer one (2000/2000/500 m),
gamma = 1/spacing^2. Training data: the flight split of the core benchmark (20% of
whole flights held out, seed 0), track-weighted as there. One more SQLite run per grid
has local noise (`bdf.noise` on the 1 km x 1 km x 125 m lattice of the core benchmark):
each tile's blob then also carries its moments.

Build = increments of all training points + one transaction writing every tile.
Cold query = a fresh process-level cache: every tile's posterior is computed (evidence
fit, factorisation, variance density). Uploads are 1,000 consecutive rows of the sample
each (tracks as they arrive), applied one after another after the accuracy run.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import os
import platform
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import accuracy, publish  # bench/ is on the path when run as a script

from bdf import BayesianDynamicField, ingest
from service.maps import RegionMaps
from service.store import open_store

GRIDS = {"core grid": ingest.PARIS_SPACING_M.tolist(), "fine grid": [2000.0, 2000.0, 500.0]}


def run_backend(url, spec, obs, test, weight, n_uploads=0) -> dict:
    store = open_store(url)
    store.create_region(spec)
    maps = RegionMaps(store, cache_mb=2048)
    train = obs.subset(~test)
    t0 = time.perf_counter()
    maps.upload("paris", "build", train.X, train.V, sample_weight=weight, replace=True)
    build_s = time.perf_counter() - t0

    Xte, Vte = obs.X[test], obs.V[test]
    q10k = Xte[np.random.default_rng(0).choice(len(Xte), 10_000, replace=False)]
    t0 = time.perf_counter()
    maps.predict("paris", q10k)
    cold_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    maps.predict("paris", q10k)
    warm_s = time.perf_counter() - t0
    pred = maps.predict("paris", Xte)
    acc = accuracy(Vte, train.V, pred.mean, pred.std)
    tiles = store.tiles("paris")
    nbytes = np.array([t.nbytes for t in tiles])

    upload_s = []
    for i in range(n_uploads):
        rows = slice(1000 * i, 1000 * (i + 1))
        t0 = time.perf_counter()
        maps.upload("paris", f"chunk-{i}", obs.X[rows], obs.V[rows])
        upload_s.append(time.perf_counter() - t0)
    store.close()
    upload_s = upload_s or [np.nan]
    return {
        "build s": build_s,
        "upload median ms": 1e3 * float(np.median(upload_s)),
        "upload p99 ms": 1e3 * float(np.percentile(upload_s, 99)),
        "query 10k cold s": cold_s,
        "query 10k warm s": warm_s,
        "tiles": len(tiles),
        "KB per tile": f"{nbytes.mean() / 1024:.0f} (max {nbytes.max() / 1024:.0f})",
        "cache MB": maps.cache.nbytes / 2**20,
        **acc,
    }


def single_field(lower, upper, spacing, obs, test, weight) -> dict:
    spacing = np.array(spacing)
    field = BayesianDynamicField(lower, upper, spacing, 1 / spacing**2, alpha="auto", beta="auto")
    train = obs.subset(~test)
    t0 = time.perf_counter()
    field.fit(train.X, train.V, sample_weight=weight)
    mean, std = field.predict(obs.X[test], return_std=True)
    seconds = time.perf_counter() - t0
    row = {"train+query s": seconds, "M": len(field.hinges), **accuracy(obs.V[test], train.V, mean, std)}
    return row, {"alpha": field.alpha_.tolist(), "beta": field.beta_.tolist()}


def table(rows: list[dict]) -> str:
    cols = list(dict.fromkeys(k for r in rows for k in r))
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c, "")
            v = "(not run)" if isinstance(v, float) and np.isnan(v) else v
            cells.append(v if isinstance(v, str) else f"{v:d}" if isinstance(v, int) else f"{v:.3f}")
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def arguments(doc: str) -> argparse.ArgumentParser:
    """The options the store benchmarks share: --postgres URL, --no-append."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--postgres", default=os.environ.get("BDF_TEST_POSTGRES_URL"), help="PostgreSQL URL")
    parser.add_argument("--no-append", action="store_true", help="do not append to bench/RESULTS.md")
    return parser


@contextlib.contextmanager
def postgres_schema(url: str):
    """A store URL on a fresh schema of the server at ``url``; the schema is dropped after."""
    schema = f"bench_{uuid.uuid4().hex[:8]}"
    try:
        yield f"{url}?schema={schema}"
    finally:
        import psycopg

        with psycopg.connect(url, autocommit=True) as conn:
            conn.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")


def main():
    parser = arguments(__doc__)
    parser.add_argument("--uploads", type=int, default=50, help="1,000-point uploads to time")
    args = parser.parse_args()

    obs, lower, upper = ingest.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    report = [
        f"## Tiled maps, {datetime.date.today()}",
        "",
        f"`{' '.join([Path(sys.executable).name, *sys.argv])}` on {platform.machine()}, "
        f"{os.cpu_count()} cores. Paris sample, {len(obs)} points; flight split (train "
        f"{int((~test).sum())}, test {int(test.sum())}); region 80 x 80 x 6 km, tiles 10 x 10 km "
        "x full altitude band, 1 km overlap, alpha = beta = auto per tile unless said, track weights. "
        "The single field at the fine grid would need 21,853 hinges: only tiles can hold it.",
    ]
    rows = []
    for grid_name, spacing in GRIDS.items():
        spec = ingest.paris_region(lower, upper, spacing)
        weight = ingest.track_weights(obs.subset(~test), spacing)
        try:
            ref, hyper = single_field(lower, upper, spacing, obs, test, weight)
            rows.append({"map": f"single field, {grid_name}", **ref})
        except ValueError as exc:  # too many hinges for one dense precision matrix
            rows.append({"map": f"single field, {grid_name}: impossible ({str(exc)[:40]}...)"})
            hyper = None
        m_tile = spec.tile_grid((3, 3, 0)).size
        with tempfile.TemporaryDirectory() as tmp:
            res = run_backend(f"sqlite:///{tmp}", spec, obs, test, weight, args.uploads)
            rows.append({"map": f"tiled, SQLite, {grid_name}", "M": m_tile, **res})
        if args.postgres:
            with postgres_schema(args.postgres) as url:
                res = run_backend(url, spec, obs, test, weight, args.uploads)
            rows.append({"map": f"tiled, PostgreSQL, {grid_name}", "M": m_tile, **res})
        local = spec.model_validate(
            {**spec.model_dump(), "noise_spacing_m": ingest.PARIS_NOISE_SPACING_M.tolist()}
        )
        with tempfile.TemporaryDirectory() as tmp:
            res = run_backend(f"sqlite:///{tmp}", local, obs, test, weight, args.uploads)
        rows.append({"map": f"tiled, SQLite, {grid_name}, local noise", "M": m_tile, **res})
        if hyper is not None:  # the same tiles with region-wide alpha, beta (the single field's evidence fit)
            pinned = spec.model_copy(update=hyper)
            with tempfile.TemporaryDirectory() as tmp:
                res = run_backend(f"sqlite:///{tmp}", pinned, obs, test, weight)
            rows.append({"map": f"tiled, SQLite, {grid_name}, region-wide alpha/beta", "M": m_tile, **res})
        print(table(rows[-4:]), flush=True)
    publish([*report, "", table(rows), ""], not args.no_append)


if __name__ == "__main__":
    main()
