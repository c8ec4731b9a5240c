"""The HTTP service under load on loopback: queries (JSON vs Arrow), grids, concurrent uploads.

    .venv/bin/python bench/bench_service.py [--postgres URL] [--seconds 10] [--workers 1] [--no-append]

A real ``bdf serve`` (``--workers`` uvicorn workers, SQLite unless --postgres) holds the Paris
map of bench_tiles.py (core grid, flight split, fitted over HTTP as one Arrow body). The load
generator is asyncio + httpx in this process (it shares the 2 cores with the server):

* queries: 1,000 random test-set points per request; one client in sequence (latency
  unloaded), then 16 concurrent clients for ``--seconds`` (throughput, p50, p99), with the
  CPU time the server (all its processes) and the load generator spent per request;
* grid: 100 x 100 x 30 voxels over the whole region, npz and Arrow, warm cache, median of 5;
* uploads: 10 concurrent uploaders, 1,000 rows each request (Arrow), distinct keys.
* library: the same 1,000-point queries through ``RegionSpec.predict`` in this process
  (median of 50): the compute inside one request.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import (  # bench/ is on the path as a script
    GRIDS,
    arguments,
    postgres_schema,
    publish,
    rows_table,
)

from bdf import ingest
from clients.local import LocalService
from service.formats import ARROW, NPZ, arrow_bytes

QUERY_POINTS = 1000
CLIENTS = 16
UPLOADERS = 10


def arrow_points(X, V=None) -> bytes:
    cols = {"x": X[:, 0], "y": X[:, 1], "z": X[:, 2]}
    if V is not None:
        cols.update(ve=V[:, 0], vn=V[:, 1], vu=V[:, 2])
    return arrow_bytes(cols)


def process_tree_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of process ``pid`` and its children (uvicorn workers)."""
    tick, total = os.sysconf("SC_CLK_TCK"), 0.0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended meanwhile
            continue
        if int(stat.parent.name) == pid or int(fields[1]) == pid:
            total += (int(fields[11]) + int(fields[12])) / tick
    return total


def stats(latencies, wall=None) -> dict:
    ms = 1e3 * np.asarray(latencies)
    out = {"requests": len(ms), "p50 ms": float(np.median(ms)), "p99 ms": float(np.percentile(ms, 99))}
    if wall:
        out["req/s"] = len(ms) / wall
    return out


def build(url: str, spec, obs, test) -> float:
    train = obs.subset(~test)
    with httpx.Client(base_url=url, timeout=600) as c:
        c.post("/v1/regions", json=spec.model_dump(mode="json")).raise_for_status()
        t0 = time.perf_counter()
        r = c.post(
            "/v1/regions/paris/fit",
            content=arrow_points(train.X, train.V),
            headers={"Content-Type": ARROW, "Idempotency-Key": "build"},
        )
        r.raise_for_status()
        while r.status_code == 202 or r.json().get("state") in ("queued", "running"):
            time.sleep(0.05)
            r = c.get(f"/v1/jobs/{r.json()['id']}")
        assert r.json().get("state", "succeeded") == "succeeded", r.json()
        return time.perf_counter() - t0


def query_bodies(points, n, fmt, seed=0):
    rng = np.random.default_rng(seed)
    bodies = []
    for _ in range(n):
        X = points[rng.choice(len(points), QUERY_POINTS, replace=False)]
        if fmt == "arrow":
            bodies.append((arrow_points(X), {"Content-Type": ARROW, "Accept": ARROW}))
        else:
            bodies.append((json.dumps({"points": X.tolist()}).encode(), {"Content-Type": "application/json"}))
    return bodies


async def query_load(url, bodies, clients, seconds) -> dict:
    latencies = []
    limits = httpx.Limits(max_connections=clients)
    async with httpx.AsyncClient(base_url=url, timeout=60, limits=limits) as c:

        async def worker(k):
            i = k
            while time.perf_counter() < stop:
                body, headers = bodies[i % len(bodies)]
                t0 = time.perf_counter()
                r = await c.post("/v1/regions/paris/query", content=body, headers=headers)
                latencies.append(time.perf_counter() - t0)
                assert r.status_code == 200, r.text
                i += clients

        start = time.perf_counter()
        stop = start + seconds
        await asyncio.gather(*(worker(k) for k in range(clients)))
        wall = time.perf_counter() - start
    return stats(latencies, wall)


async def upload_load(url, obs, uploaders, per_uploader) -> dict:
    latencies = []
    async with httpx.AsyncClient(
        base_url=url, timeout=120, limits=httpx.Limits(max_connections=uploaders)
    ) as c:

        async def worker(k):
            for j in range(per_uploader):
                rows = slice(1000 * (k * per_uploader + j), 1000 * (k * per_uploader + j + 1))
                body = arrow_points(obs.X[rows], obs.V[rows])
                t0 = time.perf_counter()
                r = await c.post(
                    "/v1/regions/paris/observations",
                    content=body,
                    headers={"Content-Type": ARROW, "Idempotency-Key": f"load-{k}-{j}"},
                )
                latencies.append(time.perf_counter() - t0)
                assert r.status_code == 200, r.text

        start = time.perf_counter()
        await asyncio.gather(*(worker(k) for k in range(uploaders)))
        wall = time.perf_counter() - start
    out = stats(latencies, wall)
    out["rows/s"] = 1000 * len(latencies) / wall
    return out


def library_query_ms(spec, obs, test, repeat=50) -> float:
    """Median ms of ``RegionSpec.predict`` at 1,000 test points on the same map, in this
    process: the compute inside one query request, without HTTP or store."""
    train = obs.subset(~test)
    increments = spec.increments(train.X, train.V)
    post = spec.posterior(spec.region_evidence({k: i.evidence for k, i in increments.items()}))
    rng = np.random.default_rng(0)
    points = obs.X[test]
    times = []
    for _ in range(repeat):
        X = points[rng.choice(len(points), QUERY_POINTS, replace=False)]
        t0 = time.perf_counter()
        spec.predict(X, post, increments)
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def grid_times(url, spec, accept, repeat=5) -> dict:
    lo, hi = spec.lower, spec.upper
    step = (hi - lo) / (np.array([100, 100, 30]) - 1)
    params = {"bbox": ",".join(map(str, [*lo, *hi])), "step": ",".join(map(str, step))}
    times = []
    with httpx.Client(base_url=url, timeout=120) as c:
        for i in range(repeat + 1):
            t0 = time.perf_counter()
            r = c.get("/v1/regions/paris/grid", params=params, headers={"Accept": accept})
            r.raise_for_status()
            if i:  # the first request warms the cache
                times.append(time.perf_counter() - t0)
    return {"voxels": 300_000, "median ms": 1e3 * float(np.median(times)), "MB": len(r.content) / 2**20}


def run(url_env: dict, data_dir, spec, obs, test, seconds) -> tuple[list[dict], float]:
    rows = []
    with LocalService(data_dir, url_env) as svc:
        fit_s = build(svc.url, spec, obs, test)
        points = obs.X[test]
        with httpx.Client(base_url=svc.url, timeout=120) as c:  # warm every tile's posterior
            for _ in range(4 * int(url_env.get("BDF_WORKERS", 1))):  # in each worker, likely
                c.post(
                    "/v1/regions/paris/query",
                    content=arrow_points(points[:20000]),
                    headers={"Content-Type": ARROW},
                )
        for fmt in ("json", "arrow"):
            bodies = query_bodies(points, 64, fmt)
            for clients, duration in ((1, seconds / 2), (CLIENTS, seconds)):
                server, client = process_tree_cpu_s(svc.proc.pid), time.process_time()
                load = asyncio.run(query_load(svc.url, bodies, clients, duration))
                load["server CPU ms/req"] = (
                    1e3 * (process_tree_cpu_s(svc.proc.pid) - server) / load["requests"]
                )
                load["client CPU ms/req"] = 1e3 * (time.process_time() - client) / load["requests"]
                rows.append(
                    {"what": f"query 1,000 pts, {fmt}, {clients} client{'s' * (clients > 1)}", **load}
                )
        for accept, name in ((NPZ, "npz"), (ARROW, "arrow")):
            g = grid_times(svc.url, spec, accept)
            rows.append({"what": f"grid 100x100x30, {name}, warm", "p50 ms": g["median ms"], "MB": g["MB"]})
        up = asyncio.run(upload_load(svc.url, obs, UPLOADERS, 10))
        rows.append({"what": f"upload 1,000 rows, arrow, {UPLOADERS} uploaders", **up})
    rows.append({"what": "query 1,000 pts, library (no HTTP)", "p50 ms": library_query_ms(spec, obs, test)})
    return rows, fit_s


def main():
    parser = arguments(__doc__)
    parser.add_argument("--seconds", type=float, default=10.0, help="duration of each concurrent query run")
    parser.add_argument("--threads", type=int, default=2, help="the service's compute threads (BDF_THREADS)")
    parser.add_argument("--workers", type=int, default=1, help="uvicorn worker processes (BDF_WORKERS)")
    args = parser.parse_args()

    obs, lower, upper = ingest.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    spec = ingest.paris_region(lower, upper, GRIDS["core grid"])
    report = [
        f"## HTTP service, {datetime.date.today()}",
        "",
        f"`{' '.join([Path(sys.executable).name, *sys.argv])}` on {platform.machine()}, "
        f"{os.cpu_count()} cores; {args.workers} uvicorn worker(s) with {args.threads} compute threads "
        "each; the load generator (asyncio + httpx) shares the machine. Paris map of bench_tiles "
        f"(core grid), fitted over HTTP from {int((~test).sum())} rows in one Arrow body. Targets: "
        "1,000-point query p50 < 20 ms with Arrow; 100x100x30 grid < 300 ms warm.",
    ]
    backends = ["SQLite", "PostgreSQL"] if args.postgres else ["SQLite"]
    for name in backends:
        env = {"BDF_LOG_LEVEL": "warning", "BDF_THREADS": str(args.threads), "BDF_WORKERS": str(args.workers)}
        with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
            if name == "PostgreSQL":
                env["BDF_STORE_URL"] = stack.enter_context(postgres_schema(args.postgres))
            rows, fit_s = run(env, tmp, spec, obs, test, args.seconds)
        report += ["", f"{name}: fit over HTTP {fit_s:.2f} s", "", rows_table(rows)]
        print(rows_table(rows), flush=True)
    publish([*report, ""], not args.no_append)


if __name__ == "__main__":
    main()
