"""The HTTP service under load on loopback: 1,000-point queries (JSON vs Arrow) driven by
``wrk``, grids, concurrent uploads, and the library's own compute for the same query.

    .venv/bin/python bench/bench_service.py [--postgres URL] [--seconds 10] [--workers 2]
        [--directions 1,8] [--model-directions 1] [--no-append]

A real ``bdf serve`` (``--workers`` uvicorn workers, SQLite unless --postgres) holds the
demo's Paris map (its lattice, ``clients.samples.paris_demo_region``; flight split, fitted over
HTTP as one Arrow body), with one class and with the demo's 8 heading sectors (one class
answers from a model of 8 sectors, or with ``--model-directions 1`` from the paper's model
of one field):

* queries: ``wrk`` (a C load generator: microseconds of CPU per request, so the server's
  cost is what is measured) POSTs the same 1,000 test points with 1, 4, 16 and 64
  connections for ``--seconds``: p50, p99, requests/s, and the server's CPU per request
  (user + system of all its processes, from /proc);
* grid: 100 x 100 x 30 voxels over the whole region, npz and Arrow, warm, median of 5 (httpx);
* uploads: 10 concurrent uploaders, 1,000 rows each request (Arrow), distinct keys (httpx);
  then the same again while wrk queries (4 connections): the queries' latency while the
  map's posterior is recomputed after each burst of uploads;
* the fixed cost of a request: ``GET /healthz`` and a 1-point Arrow query (wrk, 4 connections);
* library: the same 1,000-point query through ``RegionMap.predict`` in this process
  (median of 50): the compute inside one request, by the compiled gather queries use and
  by the blocked numpy/BLAS reference path; the same at 10,000 and 100,000 points (where
  directional tables switch to blocks; short rows stay point by point), and the
  100 x 100 x 30 grid (with directions, also with modes).

``make bench`` installs wrk with apt-get where it may (root); elsewhere install the
Debian/Ubuntu package ``wrk`` (or build it from github.com/wg/wrk).
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import (  # bench/ is on the path as a script
    arguments,
    postgres_schema,
    publish,
    rows_table,
)

from bdf import features, ingest
from bdf.region.evidence import increments, region_total
from bdf.region.map import RegionMap, compute_posterior
from clients import samples
from clients.local import LocalService
from service.formats import arrow_bytes
from service.wire import ARROW, NPZ

QUERY_POINTS = 1000
CLIENTS = 16
UPLOADERS = 10


def arrow_points(X, V=None, sample_weight=None, track=None, t=None) -> bytes:
    """An Arrow body of points (a query), with velocities an upload (and the optional columns)."""
    cols = {"x": X[:, 0], "y": X[:, 1], "z": X[:, 2]}
    if V is not None:
        cols.update(ve=V[:, 0], vn=V[:, 1], vu=V[:, 2])
    optional = {"sample_weight": sample_weight, "track": track, "t": t}
    cols.update({name: values for name, values in optional.items() if values is not None})
    return arrow_bytes(cols)


def process_tree_cpu_s(pid: int) -> dict[int, tuple[int, float]]:
    """Process ``pid`` and each of its children (uvicorn's workers): its parent and CPU
    seconds (user + system)."""
    tick, tree = os.sysconf("SC_CLK_TCK"), {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended meanwhile
            continue
        child, parent = int(stat.parent.name), int(fields[1])
        if child == pid or parent == pid:
            tree[child] = (parent, (int(fields[11]) + int(fields[12])) / tick)
    return tree


def _spawned(pid: int) -> bool:
    """Process ``pid`` is a worker that multiprocessing spawned."""
    try:
        return b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def stats(latencies, wall=None) -> dict:
    ms = 1e3 * np.asarray(latencies)
    out = {"requests": len(ms), "p50 ms": float(np.median(ms)), "p99 ms": float(np.percentile(ms, 99))}
    if wall:
        out["req/s"] = len(ms) / wall
    return out


def build(url: str, body: dict, obs, test) -> float:
    """Create the region of spec ``body`` and fit it to the training rows: seconds."""
    train = obs.subset(~test)
    with httpx.Client(base_url=url, timeout=600) as c:
        c.post("/v1/regions", json=body).raise_for_status()
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


WRK_SCRIPT = """
local path = os.getenv("BDF_BENCH_BODY")
if path ~= "" then
  local f = io.open(path, "rb")
  wrk.method = "POST"
  wrk.body = f:read("*a")
  f:close()
  wrk.headers["Content-Type"] = os.getenv("BDF_BENCH_TYPE")
  wrk.headers["Accept"] = os.getenv("BDF_BENCH_TYPE")
end
local threads = {}
setup = function(thread) table.insert(threads, thread) end
init = function(args) shed = 0 end
response = function(status, headers, body) if status == 503 then shed = shed + 1 end end
done = function(summary, latency, requests)
  local total = 0
  for _, t in ipairs(threads) do total = total + t:get("shed") end
  io.write(string.format("BDF %d %d %d %d\\n", summary.requests, summary.duration,
    latency:percentile(50), latency:percentile(99)))
  io.write(string.format("BDF_ERRORS %d %d %d\\n", summary.errors.status, summary.errors.connect
    + summary.errors.read + summary.errors.write + summary.errors.timeout, total))
end
"""


QUERY = "/v1/regions/paris/query"


def query_points(points, seed=0) -> np.ndarray:
    return points[np.random.default_rng(seed).choice(len(points), QUERY_POINTS, replace=False)]


def query_body(points, fmt) -> tuple[bytes, str]:
    X = query_points(points)
    if fmt == "arrow":
        return arrow_points(X), ARROW
    return json.dumps({"points": X.tolist()}).encode(), "application/json"


def wrk_load(
    url: str, pid: int, body: tuple[bytes, str] | None, connections: int, seconds: float, path=QUERY
) -> dict:
    """``wrk`` POSTing ``body`` (or GETting, without) to ``path`` on ``connections`` for
    ``seconds``: p50, p99, requests/s and the server's CPU per request."""
    with tempfile.TemporaryDirectory() as tmp:
        script, data = Path(tmp) / "load.lua", Path(tmp) / "body"
        script.write_text(WRK_SCRIPT)
        env = {**os.environ, "BDF_BENCH_BODY": "", "BDF_BENCH_TYPE": ""}
        if body is not None:
            data.write_bytes(body[0])
            env.update(BDF_BENCH_BODY=str(data), BDF_BENCH_TYPE=body[1])
        cmd = ["wrk", "-t1", f"-c{connections}", f"-d{seconds:g}s", "--timeout", "30s", "-s", str(script)]
        before = process_tree_cpu_s(pid)
        out = subprocess.run([*cmd, f"{url}{path}"], env=env, capture_output=True, text=True)
        after = process_tree_cpu_s(pid)
    cpu = sum(c for _, c in after.values()) - sum(c for _, c in before.values())
    # the least busy of several workers (uvicorn's children spawned by multiprocessing, not its
    # resource tracker; one worker is the server process itself), in cores: near 0 when
    # another took every connection
    workers = [p for p, (parent, _) in after.items() if parent == pid and p in before and _spawned(p)]
    busy = [(after[p][1] - before[p][1]) / seconds for p in workers]
    idlest = min(busy) if len(busy) > 1 else float("nan")
    found = re.search(r"^BDF (\d+) (\d+) (\d+) (\d+)$", out.stdout, re.M)
    errors = re.search(r"^BDF_ERRORS (\d+) (\d+) (\d+)$", out.stdout, re.M)
    # 503s are the lanes shedding load (their queue full: by design, with Retry-After); any
    # other error is a failure
    if out.returncode or not found or found.group(1) == "0" or errors is None:
        raise RuntimeError(f"wrk failed:\n{out.stdout}\n{out.stderr}")
    status, broken, shed = (int(v) for v in errors.groups())
    if broken or status != shed:
        raise RuntimeError(f"wrk saw errors other than 503 (shed):\n{out.stdout}\n{out.stderr}")
    requests, micros, p50, p99 = (int(v) for v in found.groups())
    return {
        "requests": requests,
        "shed (503)": shed,
        "p50 ms": p50 / 1e3,
        "p99 ms": p99 / 1e3,
        "req/s": requests / (micros / 1e6),
        "server CPU ms/req": 1e3 * cpu / (requests - shed),
        "idlest worker, cores": idlest,
    }


async def warm(url: str, body: bytes, timeout_s: float = 600) -> None:
    """Until every worker has the map: rounds of 16 concurrent queries on new connections
    (which the workers accept at random) until three rounds in a row answer within a second."""
    deadline, fast = time.monotonic() + timeout_s, 0
    while fast < 3:
        if time.monotonic() > deadline:
            raise RuntimeError(f"the map was not ready in every worker within {timeout_s} s")
        t0 = time.monotonic()
        async with httpx.AsyncClient(base_url=url, timeout=timeout_s) as c:
            await asyncio.gather(
                *(c.post(QUERY, content=body, headers={"Content-Type": ARROW}) for _ in range(16))
            )
        fast = fast + 1 if time.monotonic() - t0 < 1.0 else 0


async def upload_load(url, obs, uploaders, per_uploader, key="load") -> dict:
    latencies, retried = [], []
    async with httpx.AsyncClient(
        base_url=url, timeout=120, limits=httpx.Limits(max_connections=uploaders)
    ) as c:

        async def worker(k):
            for j in range(per_uploader):
                rows = slice(1000 * (k * per_uploader + j), 1000 * (k * per_uploader + j + 1))
                body = arrow_points(obs.X[rows], obs.V[rows])
                t0 = time.perf_counter()
                while True:  # as a client should: a 503 says when to retry (same key: once)
                    r = await c.post(
                        "/v1/regions/paris/observations",
                        content=body,
                        headers={"Content-Type": ARROW, "Idempotency-Key": f"{key}-{k}-{j}"},
                    )
                    if r.status_code != 503:
                        break
                    retried.append(1)
                    await asyncio.sleep(float(r.headers.get("Retry-After", 1)))
                latencies.append(time.perf_counter() - t0)
                assert r.status_code == 200, r.text

        start = time.perf_counter()
        await asyncio.gather(*(worker(k) for k in range(uploaders)))
        wall = time.perf_counter() - start
    out = stats(latencies, wall)
    out["rows/s"] = 1000 * len(latencies) / wall
    out["retried (503)"] = len(retried)
    return out


def library_rows(spec, obs, test, X) -> list[dict]:
    """The compute inside requests, in this process on the same map (no HTTP, no store):
    the 1,000-point query ``X`` the load sends, the same query at 10,000 and 100,000 test
    points (where directional tables switch to blocks), each by the compiled point-by-point gather and
    by the blocked BLAS one, interleaved so both see the same machine; and the warm
    100 x 100 x 30 grid. Medians."""
    train = obs.subset(~test)
    tile_increments = increments(spec, train.X, train.V)
    post = compute_posterior(spec, region_total(spec, {k: i.evidence for k, i in tile_increments.items()}))
    gather = features.gather
    paths = {
        "compiled, point by point": features.gather_pointwise,
        "numpy + BLAS, by blocks": features.gather_blocked,
    }
    rows = []
    try:
        for points, repeat in ((X, 50), (obs.X[test][:10_000], 10), (obs.X[:100_000], 3)):
            times = {name: [] for name in paths}
            for _ in range(repeat):
                for name, path in paths.items():
                    features.gather = lambda *a, block=1, path=path, **kw: path(*a, **kw)
                    t0 = time.perf_counter()
                    RegionMap(spec, post).predict(points)
                    times[name].append(time.perf_counter() - t0)
            for name, t in times.items():
                ms = 1e3 * float(np.median(t))
                rows.append({"what": f"query {len(points):,} pts, library (no HTTP), {name}", "p50 ms": ms})
    finally:
        features.gather = gather
    axes = spec.box_axes(spec.lower, spec.upper, (spec.upper - spec.lower) / (np.array([100, 100, 30]) - 1))
    RegionMap(spec, post).predict_grid(axes)
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        RegionMap(spec, post).predict_grid(axes)
        times.append(time.perf_counter() - t0)
    rows.append({"what": "grid 100x100x30, library (no HTTP)", "p50 ms": 1e3 * float(np.median(times))})
    if not spec.one_class:  # what a grid request with modes computes: the modes, then their moments
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            RegionMap(spec, post).predict_grid(axes, RegionMap(spec, post).predict_grid_modes(axes))
            times.append(time.perf_counter() - t0)
        rows.append(
            {"what": "grid 100x100x30 with modes, library (no HTTP)", "p50 ms": 1e3 * float(np.median(times))}
        )
    return rows


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


CONNECTIONS = (1, 4, 16, 64)


def run(url_env: dict, data_dir, spec, obs, test, seconds) -> tuple[list[dict], float]:
    rows = []
    with LocalService(data_dir, url_env, ["--workers", url_env["BDF_WORKERS"]]) as svc:
        fit_s = build(svc.url, spec.model_dump(mode="json"), obs, test)
        points = obs.X[test]
        asyncio.run(warm(svc.url, arrow_points(points[:100])))
        for fmt in ("json", "arrow"):
            body = query_body(points, fmt)
            for connections in CONNECTIONS:
                load = wrk_load(svc.url, svc.proc.pid, body, connections, seconds)
                rows.append({"what": f"query 1,000 pts, {fmt}, {connections} conn (wrk)", **load})
                print(rows[-1], flush=True)
        # the fixed cost: the HTTP stack alone, and a query of one point
        rows.append(
            {
                "what": "GET /healthz, 4 conn (wrk)",
                **wrk_load(svc.url, svc.proc.pid, None, 4, seconds, "/healthz"),
            }
        )
        one = (arrow_points(points[:1]), ARROW)
        rows.append(
            {"what": "query 1 pt, arrow, 4 conn (wrk)", **wrk_load(svc.url, svc.proc.pid, one, 4, seconds)}
        )
        for accept, name in ((NPZ, "npz"), (ARROW, "arrow")):
            g = grid_times(svc.url, spec, accept)
            rows.append({"what": f"grid 100x100x30, {name}, warm", "p50 ms": g["median ms"], "MB": g["MB"]})
        up = asyncio.run(upload_load(svc.url, obs, UPLOADERS, 10))
        rows.append({"what": f"upload 1,000 rows, arrow, {UPLOADERS} uploaders", **up})
        # queries while uploads keep the map's posterior recomputing (after each burst)
        with ThreadPoolExecutor(1) as pool:
            during = pool.submit(asyncio.run, upload_load(svc.url, obs, UPLOADERS, 10, "during"))
            time.sleep(1.0)
            load = wrk_load(svc.url, svc.proc.pid, query_body(points, "arrow"), 4, seconds)
            del load["server CPU ms/req"]  # the uploads' and refreshes' CPU is in it too
            rows.append({"what": "query 1,000 pts, arrow, 4 conn (wrk), during the uploads", **load})
            during.result()
    rows += library_rows(spec, obs, test, query_points(obs.X[test]))
    return rows, fit_s


def main():
    parser = arguments(__doc__)
    parser.add_argument("--seconds", type=float, default=10.0, help="duration of each wrk run")
    parser.add_argument("--threads", type=int, default=2, help="the service's compute threads (BDF_THREADS)")
    parser.add_argument("--workers", type=int, default=2, help="uvicorn worker processes (BDF_WORKERS)")
    parser.add_argument("--directions", default="1,8", help="heading sectors of the maps (the demo's: 8)")
    parser.add_argument(
        "--model-directions", type=int, help="the model of one class (1: the paper's one field)"
    )
    args = parser.parse_args()
    if shutil.which("wrk") is None:
        sys.exit("bench_service needs wrk: apt-get install wrk (make bench does, as root)")

    obs, lower, upper = samples.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    report = [
        f"## HTTP service, {datetime.date.today()}",
        "",
        f"`{' '.join([Path(sys.executable).name, *sys.argv])}` on {platform.machine()}, "
        f"{os.cpu_count()} cores; {args.workers} uvicorn workers with {args.threads} compute threads "
        "each; wrk (1 thread) on the same machine. The demo's Paris map (its lattice: "
        f"{samples.PARIS_REGION_SPACING_M.tolist()} m, gamma "
        f"{samples.PARIS_REGION_GAMMA[0] * samples.PARIS_REGION_SPACING_M[0] ** 2:g}/spacing^2, cutoff "
        f"{samples.PARIS_REGION_CUTOFF:g}), fitted over HTTP "
        f"from {int((~test).sum())} rows in one Arrow body. Targets (issue 20): 16 connections, Arrow, "
        "p50 < 20 ms and < 2.5 ms of server CPU per request; 1 connection p50 < 4 ms; grid < 100 ms warm.",
    ]
    backends = ["SQLite", "PostgreSQL"] if args.postgres else ["SQLite"]
    for directions in (int(d) for d in args.directions.split(",")):
        model = args.model_directions if directions == 1 else None
        spec = samples.paris_demo_region(lower, upper, directions=directions, model_directions=model)
        for name in backends:
            env = {
                "BDF_LOG_LEVEL": "warning",
                "BDF_THREADS": str(args.threads),
                "BDF_WORKERS": str(args.workers),
            }
            with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
                if name == "PostgreSQL":
                    env["BDF_STORE_URL"] = stack.enter_context(postgres_schema(args.postgres))
                rows, fit_s = run(env, tmp, spec, obs, test, args.seconds)
            report += [
                "",
                f"{name}, directions {directions} (model_directions {spec.model_directions}): "
                f"fit over HTTP {fit_s:.2f} s",
                "",
                rows_table(rows),
            ]
            print(rows_table(rows), flush=True)
    publish([*report, ""], not args.no_append)


if __name__ == "__main__":
    main()
