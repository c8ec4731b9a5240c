"""The whole service under sustained mixed load (2 uvicorn workers, 32 clients): no
unexpected answer, and the store ends holding exactly the acknowledged uploads."""

import asyncio
import os

import httpx
import pytest

from bdf.region.spec import RegionSpec
from clients.load import WEIGHTS, mixed_load, stored_difference, upload_batch
from clients.local import LocalService
from tests.service.test_store import SPEC

pytestmark = pytest.mark.slow  # a mixed load against a server

#: seconds of load per backend (bench/bench_load.py runs 60)
SECONDS = float(os.environ.get("BDF_LOAD_SECONDS", "30"))


def test_mixed_load_from_32_clients_on_2_workers_answers_everything_and_loses_nothing(store_url, tmp_path):
    spec = RegionSpec.model_validate(SPEC)
    env = {"BDF_STORE_URL": store_url}
    with LocalService(tmp_path / "data", env, ["--workers", "2"], tmp_path / "server.log") as server:
        httpx.post(f"{server.url}/v1/regions", json=SPEC, timeout=60).raise_for_status()
        X, V = upload_batch(spec, 0)
        body = {"points": X.tolist(), "velocities": V.tolist()}
        httpx.post(
            f"{server.url}/v1/regions/{spec.name}/observations",
            json=body,
            headers={"Idempotency-Key": "load-0"},
            timeout=60,
        ).raise_for_status()
        result = asyncio.run(mixed_load(server.url, spec, seconds=SECONDS, clients=32))
    assert result.unexpected == []
    assert all(result.latencies.get(kind) for kind in WEIGHTS), result.rows()
    assert len(result.acknowledged) == len(set(result.acknowledged)) > 10
    assert stored_difference(store_url, spec, [0, *result.acknowledged]) < 1e-9
    assert stored_difference(store_url, spec, result.acknowledged) == float("inf")  # the check can fail
