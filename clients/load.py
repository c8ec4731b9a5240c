"""A mixed workload against a running service, for reliability runs (bench/bench_load.py and
the suite): ``clients`` asyncio clients for ``seconds``, each picking its next request by
weight among queries (JSON and Arrow), grids, tubes, uploads and the region list.

Every answer but a 200 is counted as unexpected. Uploads carry distinct idempotency keys
and are retried with the same key until acknowledged, so the acknowledged uploads are
exactly what the store must hold afterwards: :func:`upload_batch` remakes each one from
its seed for that check.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from dataclasses import dataclass, field

import httpx
import numpy as np

from bdf.region.evidence import increments
from bdf.region.spec import RegionSpec
from service.formats import arrow_bytes
from service.store import open_store
from service.wire import ARROW, NPZ

#: request kinds and their share of the workload
WEIGHTS = {"query_json": 30, "query_arrow": 20, "grid": 10, "tubes": 10, "upload": 20, "regions": 10}
UPLOAD_POINTS = 200


def upload_batch(spec: RegionSpec, seed: int, n: int = UPLOAD_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Upload ``seed``'s points inside the region and their velocities (a smooth field)."""
    rng = np.random.default_rng(seed)
    lo, hi = spec.lower, spec.upper
    X = rng.uniform(lo, hi, (n, 3))
    u = (X - lo) / (hi - lo)
    V = np.stack([5 * np.sin(3 * u[:, 0]), 4 * np.cos(2 * u[:, 1]), u[:, 2] - 0.5], axis=1)
    return X, V + 0.3 * rng.standard_normal(X.shape)


@dataclass
class LoadResult:
    seconds: float
    latencies: dict[str, list[float]] = field(default_factory=dict)  # kind -> seconds
    statuses: Counter = field(default_factory=Counter)  # (kind, status)
    unexpected: list[str] = field(default_factory=list)
    acknowledged: list[int] = field(default_factory=list)  # upload seeds

    def rows(self) -> list[dict]:
        """Per request kind: count, requests/s, p50 and p99 in ms, unexpected answers."""
        out = []
        for kind in WEIGHTS:
            lat = np.array(self.latencies.get(kind, [np.nan])) * 1e3
            bad = sum(n for (k, status), n in self.statuses.items() if k == kind and status != 200)
            out.append(
                {
                    "route": kind,
                    "requests": len(self.latencies.get(kind, [])),
                    "req/s": round(len(self.latencies.get(kind, [])) / self.seconds, 1),
                    "p50 ms": round(float(np.percentile(lat, 50)), 1),
                    "p99 ms": round(float(np.percentile(lat, 99)), 1),
                    "unexpected": bad,
                }
            )
        return out


async def mixed_load(
    url: str,
    spec: RegionSpec,
    *,
    seconds: float = 60,
    clients: int = 32,
    seed: int = 0,
    token: str | None = None,
    first_upload_seed: int = 1_000_000,
) -> LoadResult:
    """Run the workload on region ``spec.name`` at ``url``; see the module doc."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    region = f"/v1/regions/{spec.name}"
    rng = np.random.default_rng(seed)
    kinds, weights = list(WEIGHTS), np.array(list(WEIGHTS.values()), float)
    result = LoadResult(seconds)
    next_seed = iter(range(first_upload_seed, first_upload_seed + 10**9))
    lo, hi = spec.lower, spec.upper
    query_json = {"points": rng.uniform(lo, hi, (100, 3)).tolist()}
    Xq = rng.uniform(lo, hi, (1000, 3))
    query_arrow = arrow_bytes({"x": Xq[:, 0], "y": Xq[:, 1], "z": Xq[:, 2]})
    step = ",".join(str(float(s)) for s in np.maximum((hi - lo) / 12, 1.0))

    async def one(http: httpx.AsyncClient, kind: str):
        if kind == "query_json":
            return await http.post(f"{region}/query", json=query_json)
        if kind == "query_arrow":
            return await http.post(
                f"{region}/query", content=query_arrow, headers={"Content-Type": ARROW, "Accept": ARROW}
            )
        if kind == "grid":
            return await http.get(f"{region}/grid", params={"step": step}, headers={"Accept": NPZ})
        if kind == "tubes":
            return await http.get(f"{region}/tubes", params={"step": step, "max_std_mps": 5})
        if kind == "regions":
            return await http.get("/v1/regions")
        upload_seed = next(next_seed)
        X, V = upload_batch(spec, upload_seed)
        body = {"points": X.tolist(), "velocities": V.tolist()}
        while True:  # retried with its key until acknowledged: exactly once either way
            try:
                r = await http.post(
                    f"{region}/observations", json=body, headers={"Idempotency-Key": f"load-{upload_seed}"}
                )
            except httpx.TransportError as exc:
                result.unexpected.append(f"upload {upload_seed}: {type(exc).__name__}, retried")
                continue
            if r.status_code == 200:
                result.acknowledged.append(upload_seed)
            return r

    async def client(i: int, deadline: float):
        picks = np.random.default_rng([seed, i])
        async with httpx.AsyncClient(base_url=url, headers=headers, timeout=120) as http:
            while time.monotonic() < deadline:
                kind = kinds[picks.choice(len(kinds), p=weights / weights.sum())]
                start = time.perf_counter()
                try:
                    r = await one(http, kind)
                except httpx.TransportError as exc:
                    result.unexpected.append(f"{kind}: {type(exc).__name__}")
                    continue
                result.latencies.setdefault(kind, []).append(time.perf_counter() - start)
                result.statuses[kind, r.status_code] += 1
                if r.status_code != 200:
                    result.unexpected.append(f"{kind}: {r.status_code} {r.text[:300]}")

    started = time.monotonic()
    await asyncio.gather(*(client(i, started + seconds) for i in range(clients)))
    result.seconds = time.monotonic() - started
    return result


def stored_difference(store_url: str, spec: RegionSpec, seeds: list[int]) -> float:
    """How far the region's stored statistics are from one upload of every batch of
    ``seeds``, each once: the largest difference of any tile statistic relative to that
    statistic's scale (0 up to rounding; ``inf`` if tiles or the observation count differ)."""
    batches = [upload_batch(spec, s) for s in seeds]
    X, V = np.vstack([b[0] for b in batches]), np.vstack([b[1] for b in batches])
    expected = {k: i.evidence for k, i in increments(spec, X, V).items()}
    store = open_store(store_url)
    try:
        snap = store.snapshot(spec.name)
    finally:
        store.close()
    if snap.region.observations != len(X) or set(snap.evidence) != set(expected):
        return float("inf")
    worst = 0.0
    for key, ev in expected.items():
        for got, want in zip(snap.evidence[key].classes, ev.classes, strict=True):
            for a, b in (
                (got.density, want.density),
                (got.proj, want.proj),
                (got.mass, want.mass),
                ([got.count, *got.v_sum, *got.v_sq], [want.count, *want.v_sum, *want.v_sq]),
            ):
                a, b = np.asarray(a, float), np.asarray(b, float)
                worst = max(worst, float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300)))
    return worst
