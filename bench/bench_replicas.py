"""Replicas as users run them: ``bdf serve`` processes on one PostgreSQL behind the nginx edge
(docker/nginx.conf, its upstream pointed at them), under a stream of uploads (issue 48).

    .venv/bin/python bench/bench_replicas.py --postgres URL [--replicas 3] [--seconds 60]
        [--uploaders 8] [--readers 8] [--no-append]

Data: the Paris sample's training flights (20 % of whole flights held out, seed 0), raw rows
with their ``track`` and ``t`` columns, in time order, 1,000 rows an upload (flights cut
across uploads). Region: the demo's lattice, one class, "auto" hyperparameters.

Each run starts its replicas (one uvicorn worker each) and the edge, uploads the first
batch and waits for its map, then for ``--seconds``: ``--uploaders`` clients upload through
the edge (writes to any replica), and ``--readers`` clients query 1,000 points, reader r
on replica r mod N directly, each with ``min_version`` the version its uploader's last
upload answered (read your own writes, on another replica than the one written to).
Reported per run: uploads and versions written; reads answered, and whether each answer
holds at least its ``min_version`` (the target: all); reads shed (503, with Retry-After);
maps computed and loaded per replica (``/metrics``: ``bdf_map_refreshes``,
``bdf_map_loads``); how often a version's map was computed more than once across the
replicas (the replicas' logs: "version v: map ready", by version and pass; the target: never);
and the CPU of the posterior processes (where maps are computed), summed over the
replicas. The run with ``--replicas`` is compared with one replica under the same load: the
target is total posterior CPU within 1.3x one replica's.
"""

from __future__ import annotations

import collections
import datetime
import platform
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import arguments, postgres_schema, publish, rows_table  # bench/ is on the path
from bench_service import arrow_points
from bench_stream import map_metrics
from bench_tracks import split

from clients.local import LocalService, free_port
from clients.samples import paris_demo_region

DOCKER = Path(__file__).resolve().parents[1] / "docker"
ARROW = "application/vnd.apache.arrow.stream"
NAME = "paris"
ROWS = 1000
MAP_READY = re.compile(
    r"region \S+ version (\d+): map ready in ([0-9.]+) s \(\d+ factorisations, (settled|[^)]*)\)"
)


def upload_body(train, rows) -> bytes:
    """Raw rows as a user sends them: positions, velocities, the track and its times."""
    return arrow_points(
        train.X[rows], train.V[rows], track=train.flight[rows].astype(np.int64), t=train.time[rows]
    )


class Edge:
    """docker/nginx.conf as compose mounts it, its upstream the local replicas."""

    def __init__(self, ports: list[int], workdir: Path):
        self.port = free_port()
        conf = (DOCKER / "nginx.conf").read_text()
        servers = "\n        ".join(f"server 127.0.0.1:{p};" for p in ports)
        conf = conf.replace("server service:8000;", servers).replace(
            "listen 8080;", f"listen 127.0.0.1:{self.port};"
        )
        (workdir / "logs").mkdir(exist_ok=True)
        (workdir / "nginx.conf").write_text(conf)
        extra = f"daemon off; pid {workdir}/nginx.pid; error_log {workdir}/logs/error.log;"
        nginx = "/usr/sbin/nginx"
        self.proc = subprocess.Popen(
            [nginx, "-p", str(workdir), "-c", str(workdir / "nginx.conf"), "-g", extra],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self.url = f"http://127.0.0.1:{self.port}"
        for _ in range(100):
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200:
                    return
            except httpx.TransportError:
                time.sleep(0.1)
        raise RuntimeError("nginx did not start")

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(30)


def posterior_cpu_s(pid: int) -> float:
    """CPU seconds of the posterior processes under ``pid`` (multiprocessing's spawned
    children, not its resource tracker)."""
    total = 0.0
    for child in psutil.Process(pid).children(recursive=True):
        try:
            cmd = " ".join(child.cmdline())
            if "spawn_main" in cmd and "resource_tracker" not in cmd:
                times = child.cpu_times()
                total += times.user + times.system
        except psutil.NoSuchProcess:
            continue
    return total


def run(postgres: str, replicas: int, data, seconds: float, uploaders: int, readers: int, tmp: Path) -> dict:
    train, box = data
    spec = paris_demo_region(*box, directions=1)
    order = np.argsort(train.time, kind="stable")
    batches = [order[i : i + ROWS] for i in range(0, len(order), ROWS)]
    queries = arrow_points(np.random.default_rng(3).uniform(*QUERY_BOX, (1000, 3)))
    with postgres_schema(postgres) as url:
        services = [
            LocalService(tmp / f"r{i}", {"BDF_STORE_URL": url}, args=["--workers", "1"])
            for i in range(replicas)
        ]
        edge = Edge([s.port for s in services], tmp)
        try:
            with httpx.Client(base_url=edge.url, timeout=120) as c:
                c.post("/v1/regions", json=spec.model_dump(mode="json")).raise_for_status()
                first = c.post(
                    f"/v1/regions/{NAME}/observations",
                    content=upload_body(train, batches[0]),
                    headers={"Content-Type": ARROW, "Idempotency-Key": "b0"},
                )
                first.raise_for_status()
                for s in services:  # every replica has the first map before the load
                    httpx.post(
                        f"{s.url}/v1/regions/{NAME}/query?min_version=1",
                        content=queries,
                        headers={"Content-Type": ARROW, "Accept": ARROW},
                        timeout=300,
                    )
            cpu0 = [posterior_cpu_s(s.proc.pid) for s in services]
            written = [1] * uploaders  # the version each uploader's last upload answered
            counts = collections.Counter()
            stop = time.monotonic() + seconds
            next_batch = iter(range(1, len(batches)))
            lock = threading.Lock()

            def upload(k):
                with httpx.Client(base_url=edge.url, timeout=120) as c:
                    while time.monotonic() < stop:
                        with lock:
                            b = next(next_batch, None)
                        if b is None:
                            return
                        r = c.post(
                            f"/v1/regions/{NAME}/observations",
                            content=upload_body(train, batches[b]),
                            headers={"Content-Type": ARROW, "Idempotency-Key": f"b{b}"},
                        )
                        with lock:
                            counts[f"upload {r.status_code}"] += 1
                            if r.status_code == 200:
                                written[k] = max(written[k], r.json()["region_version"])

            def read(r):
                service = services[r % replicas]
                with httpx.Client(base_url=service.url, timeout=120) as c:
                    while time.monotonic() < stop:
                        wanted = written[r % uploaders]
                        got = c.post(
                            f"/v1/regions/{NAME}/query?min_version={wanted}",
                            content=queries,
                            headers={"Content-Type": ARROW, "Accept": ARROW},
                        )
                        with lock:
                            if got.status_code == 200:
                                ok = int(got.headers["X-Region-Version"]) >= wanted
                                counts[f"read r{r % replicas} {'holds' if ok else 'MISSES'} min_version"] += 1
                            else:
                                counts[f"read r{r % replicas} {got.status_code}"] += 1
                                time.sleep(float(got.headers.get("Retry-After", 1)))

            threads = [threading.Thread(target=upload, args=(k,)) for k in range(uploaders)]
            threads += [threading.Thread(target=read, args=(r,)) for r in range(readers)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            time.sleep(1.0)
            cpu = [posterior_cpu_s(s.proc.pid) - c0 for s, c0 in zip(services, cpu0, strict=True)]
            metrics = [map_metrics(httpx.get(f"{s.url}/metrics", timeout=10).text) for s in services]
        finally:
            edge.stop()
            for s in services:
                s.stop()
        passes = collections.Counter()
        for s in services:
            for version, _, kind in MAP_READY.findall(s.log()):
                passes[(int(version), kind == "settled")] += 1
    reads_ok = sum(v for k, v in counts.items() if "holds" in k)
    return {
        "replicas": replicas,
        "uploads": counts["upload 200"],
        "upload errors": sum(v for k, v in counts.items() if k.startswith("upload") and k != "upload 200"),
        "reads answered": reads_ok + sum(v for k, v in counts.items() if "MISSES" in k),
        "of them missing min_version": sum(v for k, v in counts.items() if "MISSES" in k),
        "reads shed (503)": sum(v for k, v in counts.items() if k.endswith(" 503")),
        "reads per replica": " / ".join(
            str(sum(v for k, v in counts.items() if k.startswith(f"read r{i} "))) for i in range(replicas)
        ),
        "maps computed (per replica)": " / ".join(f"{m.get('bdf_map_refreshes', 0):g}" for m in metrics),
        "maps loaded (per replica)": " / ".join(f"{m.get('bdf_map_loads', 0):g}" for m in metrics),
        "versions computed twice": sum(n > 1 for n in passes.values()),
        "posterior CPU [s] (per replica)": " / ".join(f"{x:.1f}" for x in cpu),
        "posterior CPU [s]": sum(cpu),
    }


QUERY_BOX = ([-30_000.0, -30_000.0, 0.0], [30_000.0, 30_000.0, 5_000.0])


def main(argv=None) -> int:
    parser = arguments(__doc__.splitlines()[0])
    parser.add_argument("--replicas", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--uploaders", type=int, default=8)
    parser.add_argument("--readers", type=int, default=8)
    args = parser.parse_args(argv)
    if not args.postgres:
        parser.error("--postgres URL (or BDF_TEST_POSTGRES_URL) is required: replicas share PostgreSQL")
    train, _, lower, upper = split()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in (1, args.replicas):
            rows.append(
                run(
                    args.postgres,
                    n,
                    (train, (lower, upper)),
                    args.seconds,
                    args.uploaders,
                    args.readers,
                    Path(tmp) / f"n{n}",
                )
            )
            print(rows[-1], flush=True)
    ratio = rows[1]["posterior CPU [s]"] / max(rows[0]["posterior CPU [s]"], 1e-9)
    report = [
        "",
        f"## Replicas on one PostgreSQL behind the edge, {datetime.date.today()}",
        "",
        f"`python bench/bench_replicas.py --replicas {args.replicas} --seconds {args.seconds:g} "
        f"--uploaders {args.uploaders} --readers {args.readers}` ({platform.node()}, "
        f"{psutil.cpu_count()} cores). Paris training flights, raw rows with track and t, 1,000 rows an "
        "upload through nginx; readers on each replica with min_version = their uploader's last version.",
        "",
        rows_table(rows),
        "",
        f"Posterior CPU of {args.replicas} replicas / one replica under the same load: **{ratio:.2f}** "
        "(target <= 1.3).",
    ]
    publish(report, not args.no_append)
    return 0


if __name__ == "__main__":
    sys.exit(main())
