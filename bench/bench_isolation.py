"""Isolation (issue 37): what one request costs in memory, and what the others see while a
heavy, slow or unlucky request runs.

    .venv/bin/python bench/bench_isolation.py [--parts memory,stress] [--no-append]

``memory``: peak RSS of the serving process answering one request (each in a fresh
process, over the RSS with the map ready), per number the answer holds, for the answers
whose size a client chooses: point queries with modes (JSON, Arrow), grids with modes
(npz), slices. ``service.formats.BYTES_PER_NUMBER`` is set from these figures, with room.

``maps``: peak RSS of computing a map with data over its whole lattice (the worst fill),
at 2,250, 4,840 and 10,240 hinges x 872 offsets with 9 classes, and 4,840 with 33, each in a
fresh process (about 20 minutes): what ``bdf.region.spec.MAP_BYTES_PER_COUPLING`` (per
coupling of one factor) and ``MAP_BYTES_PER_CLASS_HINGE`` are set from.

``stress``: ``bdf serve`` (2 light threads, 1 heavy) on loopback; while each stress of the
issue's table runs, a prober measures ``/healthz`` and a cached 1,000-point query of
another region (p50, p99, max, and how many were shed with 503), and the peak RSS of the
server's processes is sampled.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import publish, rows_table  # bench/ is on the path

ROOT = Path(__file__).resolve().parents[1]


# -- memory -----------------------------------------------------------------------------------
MEMORY_CASE = r"""
import json, sys, threading, time, tempfile
import numpy as np, psutil
sys.path.insert(0, {root!r}); sys.path.insert(0, {bench!r})
from fastapi.testclient import TestClient
from tests.service.test_isolation import EMPTY, traffic
MODES_SPEC = {{**EMPTY, "name": "modes"}}  # 16 sectors (17 classes): answers are large
from service.app import create_app
from service.settings import Settings
from service.wire import ARROW, NPZ, JSON
case, size = sys.argv[1], int(sys.argv[2])
proc = psutil.Process()
with tempfile.TemporaryDirectory() as tmp:
    app = create_app(Settings(store_url=f"sqlite:///{{tmp}}", request_memory_mb=1e6,
                              max_query_points=10**7, max_grid_voxels=10**8, max_json_voxels=10**8,
                              max_json_mb=1e4, request_timeout_s=600))
    with TestClient(app) as c:
        c.post("/v1/regions", json=MODES_SPEC).raise_for_status()
        X, V = traffic(20000, 1)
        c.post("/v1/regions/modes/observations", json={{"points": X.tolist(), "velocities": V.tolist()}},
               headers={{"Idempotency-Key": "a"}}).raise_for_status()
        c.post("/v1/regions/modes/query?min_version=1", json={{"points": X[:10].tolist()}}).raise_for_status()
        Q = traffic(size, 2)[0]
        if case.startswith("query"):
            media = ARROW if case.endswith("arrow") else JSON
            if media == ARROW:
                import pyarrow as pa
                from service.formats import arrow_bytes
                body = arrow_bytes({{"x": Q[:, 0].copy(), "y": Q[:, 1].copy(), "z": Q[:, 2].copy()}})
                send = dict(content=body, headers={{"Content-Type": ARROW, "Accept": ARROW}})
            else:
                send = dict(json={{"points": Q.tolist()}})
            del Q
        base, peak = proc.memory_info().rss, [0]
        stop = threading.Event()
        def sample():
            while not stop.is_set():
                peak[0] = max(peak[0], proc.memory_info().rss); time.sleep(0.002)
        t = threading.Thread(target=sample); t.start()
        if case.startswith("query"):
            r = c.post("/v1/regions/modes/query?modes=true", **send)
            rows = size
        else:
            n = round(size ** (1 / 3))
            step = [4000 / n, 4000 / n, 600 / n]
            r = c.get("/v1/regions/modes/grid", params={{"step": ",".join(map(str, step)), "modes": "true"}},
                      headers={{"Accept": NPZ}})
            rows = (n + 1) ** 3
        stop.set(); t.join()
        assert r.status_code == 200, r.text
        peak_mb, body_mb = (peak[0] - base) / 2**20, len(r.content) / 2**20
        print(json.dumps({{"rows": rows, "peak_mb": peak_mb, "body_mb": body_mb}}))
"""


def memory_rows() -> list[dict]:
    script = MEMORY_CASE.format(root=str(ROOT), bench=str(ROOT / "bench"))
    rows = []
    classes = 17
    numbers = 7 + 8 * classes + 1
    for case, size in (
        ("query-json", 5000),
        ("query-json", 20000),
        ("query-arrow", 20000),
        ("query-arrow", 80000),
        ("grid-npz", 20000),
        ("grid-npz", 80000),
    ):
        out = subprocess.run([sys.executable, "-c", script, case, str(size)], capture_output=True, text=True)
        if out.returncode:
            raise RuntimeError(out.stderr[-3000:])
        got = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(
            {
                "answer": case,
                "rows": got["rows"],
                "numbers": got["rows"] * numbers,
                "peak MB": round(got["peak_mb"], 1),
                "body MB": round(got["body_mb"], 1),
                "peak B/number": round(got["peak_mb"] * 2**20 / (got["rows"] * numbers), 1),
            }
        )
        print(rows[-1], flush=True)
    return rows


MAP_CASE = r"""
import json, resource, sys, time
import numpy as np
sys.path.insert(0, {root!r})
from bdf.region.spec import RegionSpec
from bdf.region.evidence import increments, region_total
from bdf.region.map import compute_posterior
nx, directions = int(sys.argv[1]), int(sys.argv[2])
spec = RegionSpec.model_validate({{
    "name": "full", "origin": {{"lat": 48.0, "lon": 2.0}},
    "bounds_m": {{"min": [0, 0, 0], "max": [500 * (nx - 1), 500 * (nx - 1), 900]}},
    "tile_size_m": [5000, 5000, 900], "spacing_m": [500, 500, 100],
    "gamma": [4e-6, 4e-6, 1e-4], "directions": directions}})
rng = np.random.default_rng(0)
X = rng.uniform(spec.lower, spec.upper, (30000, 3))  # over the whole lattice: the worst fill
heading = rng.integers(0, directions, len(X)) * 2 * np.pi / directions  # every class full
V = np.stack([40 * np.sin(heading), 40 * np.cos(heading), rng.normal(0, 1, len(X))], 1)
evidence = region_total(spec, {{k: i.evidence for k, i in increments(spec, X, V).items()}})
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
t = time.perf_counter()
compute_posterior(spec, evidence)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({{"hinges": spec.grid.size, "offsets": spec.coupled_offsets,
                  "classes": spec.sectors.classes, "couplings": spec.couplings, "estimate": spec.map_bytes,
                  "s": time.perf_counter() - t, "base_mb": base, "peak_mb": peak}}))
"""


def map_rows() -> list[dict]:
    """Peak RSS of computing a region's map with data over its whole lattice (the factor's
    largest fill), each in a fresh process: what ``MAP_BYTES_PER_COUPLING`` and
    ``MAP_BYTES_PER_CLASS_HINGE`` are set from (the classes' factors come one at a time)."""
    rows = []
    for nx, directions in ((15, 8), (22, 8), (32, 8), (22, 32)):
        out = subprocess.run(
            [sys.executable, "-c", MAP_CASE.format(root=str(ROOT)), str(nx), str(directions)],
            capture_output=True,
            text=True,
        )
        if out.returncode:
            raise RuntimeError(out.stderr[-3000:])
        got = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(
            {
                "hinges": got["hinges"],
                "offsets": got["offsets"],
                "classes": got["classes"],
                "couplings": got["couplings"],
                "map s": round(got["s"], 1),
                "peak RSS MB": round(got["peak_mb"]),
                "B per coupling": round(got["peak_mb"] * 2**20 / got["couplings"], 1),
                "estimate MB": round(got["estimate"] / 2**20),
            }
        )
        print(rows[-1], flush=True)
    return rows


def _percentiles(seconds: list[float]) -> str:
    if not seconds:
        return "(none)"
    return " / ".join(f"{1e3 * np.percentile(seconds, q):.1f}" for q in (50, 99, 100))


def stress_rows() -> list[dict]:
    """tests/service/test_isolation.py's stresses, with the prober's figures."""
    from tests.service.test_isolation import STRESSES, run_stress, stress_server

    rows = []
    with tempfile.TemporaryDirectory() as tmp, stress_server(Path(tmp)) as (svc, query):
        for stress in STRESSES:
            prober, results = run_stress(svc, query, stress)
            rows.append(
                {
                    "stress": stress,
                    "its answers": ", ".join(f"{r.status_code} in {t:.1f} s" for r, t in results),
                    "healthz p50 / p99 / max ms": _percentiles(prober.health),
                    "cached query p50 / p99 / max ms": _percentiles(prober.answers),
                    "queries answered / shed": f"{len(prober.answers)} / {len(prober.shed)}",
                    "peak RSS MB": round(prober.rss_mb),
                }
            )
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="memory,stress")
    parser.add_argument("--no-append", action="store_true")
    args = parser.parse_args()
    parts = args.parts.split(",")
    sections = []
    if "memory" in parts:
        sections.append(("Memory per answer (16 sectors, 17 classes)", rows_table(memory_rows())))
    if "maps" in parts:
        sections.append(("Computing a map, data over the whole lattice (8 sectors)", rows_table(map_rows())))
    if "stress" in parts:
        sections.append(("What the others see during each stress", rows_table(stress_rows())))
    report = [
        f"\n## Isolation, {datetime.date.today().isoformat()} (issue 37)\n",
        f"`python bench/bench_isolation.py --parts {args.parts}` on {platform.node()} "
        f"({platform.processor() or platform.machine()}, 2 cores)\n",
    ]
    for title, table in sections:
        report += [f"{title}:\n", table, ""]
    publish(report, not args.no_append)


if __name__ == "__main__":
    main()
