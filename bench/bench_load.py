"""Reliability under sustained mixed load: 32 clients for 60 s against ``bdf serve --workers 2``
on SQLite and on PostgreSQL (clients.load: queries in JSON and Arrow, grids, tubes, uploads,
region listing), then a check that the store holds exactly the acknowledged uploads.

    .venv/bin/python bench/bench_load.py [--seconds 60] [--clients 32] [--postgres URL] [--no-append]

The load generator is asyncio + httpx in this process and shares the 2 cores with the
server's 2 workers, so throughputs are a floor. The region is the suite's small town
(tests/service/test_store.py: 300 x 200 x 60 m, 6 tiles), so the figures measure the
service, not the model.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import platform
import sys
import tempfile
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import arguments, postgres_schema, publish, rows_table  # bench/ is on the path

from bdf.region.spec import RegionSpec
from clients.load import mixed_load, stored_difference, upload_batch
from clients.local import LocalService
from tests.service.test_store import SPEC  # the suite's small town


def run(store_url: str, seconds: float, clients: int) -> tuple[list[dict], dict]:
    spec = RegionSpec.model_validate(SPEC)
    with tempfile.TemporaryDirectory() as tmp:
        env = {"BDF_STORE_URL": store_url, "BDF_LOG_LEVEL": "warning"}
        with LocalService(Path(tmp) / "data", env, ["--workers", "2"]) as server:
            httpx.post(f"{server.url}/v1/regions", json=SPEC, timeout=60).raise_for_status()
            X, V = upload_batch(spec, 0)
            httpx.post(
                f"{server.url}/v1/regions/{spec.name}/observations",
                json={"points": X.tolist(), "velocities": V.tolist()},
                headers={"Idempotency-Key": "load-0"},
                timeout=60,
            ).raise_for_status()
            result = asyncio.run(mixed_load(server.url, spec, seconds=seconds, clients=clients))
        difference = stored_difference(store_url, spec, [0, *result.acknowledged])
    summary = {
        "requests": sum(len(v) for v in result.latencies.values()),
        "unexpected": len(result.unexpected),
        "uploads acknowledged": len(result.acknowledged),
        "stored - acknowledged (relative)": f"{difference:.1e}",
    }
    for line in result.unexpected[:10]:
        print("unexpected:", line)
    return result.rows(), summary


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--seconds", type=float, default=60)
    parser.add_argument("--clients", type=int, default=32)
    args = parser.parse_args()
    today = datetime.date.today().isoformat()
    report = [
        f"## Mixed load, {today} (issue 19)",
        "",
        f"`python bench/bench_load.py --seconds {args.seconds:g} --clients {args.clients}` on "
        f"{platform.machine()}, 2 cores, Python {platform.python_version()}: `bdf serve --workers 2`, "
        "the load generator in the same machine.",
        "",
    ]
    backends = [("SQLite", None)] + ([("PostgreSQL", args.postgres)] if args.postgres else [])
    for name, url in backends:
        with contextlib.ExitStack() as stack:
            if url is None:
                tmp = stack.enter_context(tempfile.TemporaryDirectory())
                store_url = f"sqlite:///{tmp}/store"
            else:
                store_url = stack.enter_context(postgres_schema(url))
            rows, summary = run(store_url, args.seconds, args.clients)
        report += [f"### {name}", "", rows_table(rows), "", rows_table([summary]), ""]
    publish(report, not args.no_append)


if __name__ == "__main__":
    main()
