"""Isolation (RELIABILITY.md, "Isolation"): one slow client, one heavy request or a stalled
database never stalls the others.

Each stress of the table runs against ``bdf serve`` on loopback while a prober asks for
``/healthz`` and a cached 1,000-point query of another region, one after the other: health
answers within 50 ms at p99, the query within 200 ms at p99 or is shed with 503 and
``Retry-After`` (by design, counted), no request stays open past its deadline, and no
process of the service grows above the memory budget."""

import concurrent.futures
import contextlib
import json
import logging
import os
import socket
import subprocess
import sys
import threading
import time
import types
import uuid

import httpx
import numpy as np
import psutil
import pytest
from fastapi.testclient import TestClient

from clients.local import LocalService, free_port
from service.app import create_app
from service.formats import arrow_bytes
from service.settings import Settings
from service.wire import ARROW, JSON, NPZ
from tests.service.conftest import POSTGRES_ENV
from tests.service.tcp_proxy import PausableProxy
from tests.service.test_store import SPEC, data

pytestmark = pytest.mark.slow  # stress servers on loopback

TIMEOUT_S = 8.0  # the request deadline of the stress server
MEMORY_MB = 1024  # the memory budget (the default): no process of the service above it
#: a directional region whose maps take seconds: 21 x 21 x 7 hinges, 8 sectors
HEAVY = {
    "name": "heavy",
    "origin": {"lat": 48.0, "lon": 2.0},
    "bounds_m": {"min": [0, 0, 0], "max": [4000, 4000, 600]},
    "tile_size_m": [2000, 2000, 600],
    "spacing_m": [200, 200, 100],
    "gamma": [1 / 20000, 1 / 20000, 1 / 5000],
    "directions": 8,
}
EMPTY = {**HEAVY, "name": "empty", "directions": 16}


def traffic(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Eight headings at 30-60 m/s over the heavy region."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(0, 1, (n, 3)) * np.array(HEAVY["bounds_m"]["max"], float)
    heading = rng.integers(0, 8, n) * (np.pi / 4)
    speed = rng.uniform(30, 60, n)
    return X, np.stack([speed * np.sin(heading), speed * np.cos(heading), rng.normal(0, 1, n)], axis=1)


def post_json(http, path, body, headers=None, **kw):
    headers = {"Content-Type": "application/json", **(headers or {})}
    return http.post(path, content=json.dumps(body), headers=headers, **kw)


class Prober:
    """Asks, one after the other, for /healthz and a cached 1,000-point query of ``town``;
    samples the RSS of the server's processes."""

    def __init__(self, server: LocalService, query: bytes):
        self.server, self.query = server, query
        self.health, self.answers, self.shed, self.rss_mb = [], [], [], 0.0
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._probe), threading.Thread(target=self._sample)]

    def __enter__(self):
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        for t in self._threads:
            t.join(60)

    def _probe(self):
        headers = {"Content-Type": ARROW, "Accept": ARROW}
        with httpx.Client(base_url=self.server.url, timeout=30) as http:
            while not self._stop.is_set():
                t = time.perf_counter()
                assert http.get("/healthz").status_code == 200
                self.health.append(time.perf_counter() - t)
                t = time.perf_counter()
                r = http.post("/v1/regions/town/query", content=self.query, headers=headers)
                took = time.perf_counter() - t
                if r.status_code == 503:
                    assert int(r.headers["retry-after"]) > 0
                    self.shed.append(took)
                else:
                    assert r.status_code == 200, r.text
                    self.answers.append(took)
                time.sleep(0.01)

    def _sample(self):
        proc = psutil.Process(self.server.proc.pid)
        while not self._stop.is_set():
            with contextlib.suppress(psutil.Error):
                for p in [proc, *proc.children(recursive=True)]:
                    self.rss_mb = max(self.rss_mb, p.memory_info().rss / 2**20)
            time.sleep(0.02)

    def check(self):
        """The acceptance: health p99 < 50 ms; the cached query p99 < 200 ms or shed; no
        process above the memory budget."""
        assert len(self.health) >= 10 and len(self.answers) >= 5, (len(self.health), len(self.answers))
        assert np.percentile(self.health, 99) < 0.05, sorted(self.health)[-5:]
        assert np.percentile(self.answers, 99) < 0.2, sorted(self.answers)[-5:]
        assert all(s < 0.2 for s in self.shed)  # shed at once, never queued
        assert self.rss_mb < MEMORY_MB, self.rss_mb


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with stress_server(tmp_path_factory.mktemp("isolation")) as out:
        yield out


@contextlib.contextmanager
def stress_server(tmp):
    """``bdf serve`` with 2 light threads and 1 heavy (queue 1), an 8 s deadline: ``town``
    (map ready), ``heavy`` (8 sectors, 30,000 observations) and ``empty`` (16 sectors);
    yields it and the prober's 1,000-point query (Arrow)."""
    env = {"BDF_REQUEST_TIMEOUT_S": str(TIMEOUT_S), "BDF_HEAVY_QUEUE": "1", "BDF_LOG_LEVEL": "warning"}
    with (
        LocalService(tmp / "data", env, log_path=tmp / "server.log") as svc,
        httpx.Client(base_url=svc.url, timeout=120) as http,
    ):
        for spec in (SPEC, HEAVY, EMPTY):
            http.post("/v1/regions", json=spec).raise_for_status()
        X, V = data(1, n=300)
        post_json(
            http,
            "/v1/regions/town/observations",
            {"points": X.tolist(), "velocities": V.tolist()},
            headers={"Idempotency-Key": "t"},
        )
        X, V = traffic(30000, 1)
        body = arrow_bytes(
            {"x": X[:, 0], "y": X[:, 1], "z": X[:, 2], "ve": V[:, 0], "vn": V[:, 1], "vu": V[:, 2]}
        )
        http.post(
            "/v1/regions/heavy/observations",
            content=body,
            headers={"Content-Type": ARROW, "Idempotency-Key": "h"},
        ).raise_for_status()
        Q = data(2, n=1000)[0]
        query = arrow_bytes({"x": Q[:, 0], "y": Q[:, 1], "z": Q[:, 2]})
        for region in ("town", "heavy"):  # both maps ready (the heavy one's first takes longer
            for _ in range(30):  # than a deadline: 503 until it is)
                r = http.post(
                    f"/v1/regions/{region}/query?min_version=1",
                    content=query,
                    headers={"Content-Type": ARROW},
                )
                if r.status_code != 503:
                    break
            r.raise_for_status()

        yield svc, query


def heavy_upload(http, key: str):
    """A new version of ``heavy``: its map is to be computed again."""
    X, V = traffic(200, hash(key) % 1000)
    return post_json(
        http,
        "/v1/regions/heavy/observations",
        {"points": X.tolist(), "velocities": V.tolist()},
        headers={"Idempotency-Key": key},
    )


def hyperparameter_fits(http):
    heavy_upload(http, uuid.uuid4().hex).raise_for_status()
    return [lambda: http.post("/v1/regions/heavy/hyperparameters")] * 2


def big_mode_queries(http):
    Q = traffic(50000, 3)[0]
    body = arrow_bytes({"x": Q[:, 0], "y": Q[:, 1], "z": Q[:, 2]})
    headers = {"Content-Type": ARROW, "Accept": ARROW}
    return [lambda: http.post("/v1/regions/heavy/query?modes=true", content=body, headers=headers)] * 2


def empty_region_query(http):
    body = json.dumps({"points": traffic(10, 4)[0].tolist()})  # encoded before the prober starts
    return [lambda: http.post("/v1/regions/empty/query", content=body, headers={"Content-Type": JSON})]


def json_mode_query(http):
    body = json.dumps({"points": traffic(50000, 5)[0].tolist()})
    return [
        lambda: http.post("/v1/regions/heavy/query?modes=true", content=body, headers={"Content-Type": JSON})
    ]


def huge_mode_grid(http):
    params = {"step": "20,20,10", "modes": "true"}  # 1.2 M voxels x 9 classes
    return [lambda: http.get("/v1/regions/heavy/grid", params=params, headers={"Accept": NPZ})]


def longest_routes(http):
    """The worst accepted assessment: a vehicle turning on a coin (the envelope sampled every
    metre) on the longest zig-zag across ``heavy`` a request may read (just under
    ``max_query_points`` of cost), four at once."""
    from bdf.region.route import ENVELOPE_SAMPLES_PER_POINT, Vehicle, samples

    coin = {"cruise_mps": 60.0, "min_turn_radius_m": 0.01, "max_climb_deg": 8.0, "max_descent_deg": 8.0}
    coin.update(floor_m=0.0, ceiling_m=600.0)
    limit = Settings().max_query_points

    def route(legs):
        return np.array([[4000.0 * (i % 2), 4000.0 * i / legs, 300.0] for i in range(legs + 1)])

    def cost(legs):
        on_map, on_envelope = samples(route(legs), Vehicle(**coin))
        return on_map + on_envelope // ENVELOPE_SAMPLES_PER_POINT

    legs = max(n for n in range(1, 1000) if cost(n) <= limit)
    body = json.dumps({"points": route(legs).tolist(), "max_std_mps": 5.0, "vehicle": coin})
    return [
        lambda: http.post("/v1/regions/heavy/routes/assess", content=body, headers={"Content-Type": JSON})
    ] * 4


def huge_headers(http):
    """Two requests with a 64 MB header value each, no token (they stalled /healthz 3.3 s)."""
    port = httpx.URL(str(http.base_url)).port
    # made before the prober starts: copying 64 MB holds this process's GIL, and the prober's
    # own threads (not the server) would wait for it
    request = b"GET /v1/regions HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 64_000_000 + b"\r\n\r\n"

    def send():
        with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
            with contextlib.suppress(OSError):  # the server answers 431 and closes before the end
                sock.sendall(request)
            answer = b""
            with contextlib.suppress(OSError):
                while chunk := sock.recv(65536):
                    answer += chunk
        return types.SimpleNamespace(
            status_code=int(answer.split(b" ", 2)[1]), headers={}, text=answer.decode()
        )

    return [send] * 2


STRESSES = {
    "two hyperparameter fits": (hyperparameter_fits, {200, 503}),
    "two 50,000-point mode queries": (big_mode_queries, {200, 503}),
    "a query of an empty 16-sector region": (empty_region_query, {200, 503}),
    "a 50,000-point JSON query with modes": (json_mode_query, {200, 503}),
    "a 1.2 M-voxel grid with modes": (huge_mode_grid, {422}),
    "four assessments of the longest route, a vehicle turning on a coin": (longest_routes, {200, 503}),
    "two 64 MB header values": (huge_headers, {431}),
}


def run_stress(svc: LocalService, query: bytes, stress: str) -> tuple[Prober, list]:
    """The prober's view while ``stress`` runs, and the stress's (response, seconds)."""
    make, _ = STRESSES[stress]
    with httpx.Client(base_url=svc.url, timeout=60) as http:
        calls = make(http)
        with Prober(svc, query) as prober, concurrent.futures.ThreadPoolExecutor(len(calls)) as pool:
            time.sleep(0.3)  # the prober's first answers come before the stress

            def timed(call):
                t = time.perf_counter()
                r = call()
                return r, time.perf_counter() - t

            results = list(pool.map(timed, calls))
            time.sleep(0.3)
    return prober, results


@pytest.mark.parametrize("stress", list(STRESSES))
def test_a_stress_does_not_stall_the_others(server, stress):
    svc, query = server
    prober, results = run_stress(svc, query, stress)
    _, statuses = STRESSES[stress]
    for r, took in results:
        assert r.status_code in statuses, r.text[:300]
        assert took < TIMEOUT_S + 1.0  # no request open past its deadline
        if r.status_code == 503:
            assert int(r.headers["retry-after"]) > 0
    if stress == "a 1.2 M-voxel grid with modes":
        assert "MiB" in results[0][0].json()["detail"]
    prober.check()


def test_half_open_connections_do_not_starve_authorised_clients(live_server):
    """Twice the connection cap of half-open clients (a partial request line, a body that
    stops): authorised requests keep being served, and the half-open ones are dropped."""
    svc = live_server(env={"BDF_MAX_CONNECTIONS": "40", "BDF_HEADER_TIMEOUT_S": "2"})
    held = []
    for i in range(80):
        sock = socket.create_connection(("127.0.0.1", svc.port))
        if i % 2:
            sock.sendall(b"GET /v1/regions HTTP/1.1\r\nHost: x\r\n")  # no end of headers
        else:
            sock.sendall(b"POST /v1/regions HTTP/1.1\r\nHost: x\r\nContent-Length: 1000\r\n\r\n{")
        held.append(sock)
    statuses = [httpx.get(f"{svc.url}/v1/regions", timeout=5).status_code for _ in range(20)]
    assert statuses == [200] * 20
    open_now = len(psutil.Process(svc.proc.pid).net_connections(kind="tcp"))
    assert open_now <= 40 + 2  # the cap (and the listener), never the 80
    time.sleep(2.5)  # the header deadline, and the longest pause of a body: all are gone
    established = [
        c for c in psutil.Process(svc.proc.pid).net_connections(kind="tcp") if c.status != "LISTEN"
    ]
    assert established == []
    dropped = 0
    for sock in held:
        sock.settimeout(1)
        with contextlib.suppress(OSError):
            dropped += sock.recv(1) == b""
    assert dropped == 80
    for sock in held:
        sock.close()


def test_a_500_is_one_log_line_with_its_traceback_and_closes_the_connection(tmp_path, caplog, monkeypatch):
    app = create_app(Settings(store_url=f"sqlite:///{tmp_path}"))
    with TestClient(app, raise_server_exceptions=False) as client:
        client.post("/v1/regions", json=SPEC).raise_for_status()
        monkeypatch.setattr(app.state.service.maps.store, "list_regions", lambda: 1 / 0)
        with caplog.at_level(logging.INFO):
            r = client.get("/v1/regions", headers={"X-Request-ID": "boom-1"})
    assert r.status_code == 500 and r.headers["connection"] == "close"
    assert r.json()["request_id"] == "boom-1" and "ZeroDivisionError" not in r.text
    errors = [rec for rec in caplog.records if rec.levelno >= logging.ERROR]
    assert len(errors) == 1 and "boom-1" in errors[0].getMessage() and errors[0].exc_info is not None


def test_every_worker_writes_the_access_log(live_server):
    svc = live_server(args=["--workers", "2"])
    for _ in range(20):
        httpx.get(f"{svc.url}/v1/regions", timeout=10).raise_for_status()
    time.sleep(0.5)
    lines = [json.loads(line) for line in svc.log().splitlines() if line.startswith('{"method"')]
    assert sum(line["route"] == "/v1/regions" for line in lines) == 20


def _workers_listening(svc, count: int) -> dict[int, psutil.Process]:
    """The service's worker processes once ``count`` of them listen on its port."""
    deadline = time.monotonic() + 60
    while True:
        workers = {p.pid: p for p in psutil.Process(svc.proc.pid).children(recursive=True)}
        listening = {
            pid: p
            for pid, p in workers.items()
            if any(
                c.status == psutil.CONN_LISTEN and c.laddr.port == svc.port for c in p.net_connections("tcp")
            )
        }
        if len(listening) == count:
            return listening
        assert time.monotonic() < deadline, f"{len(listening)} of {count} workers listen"
        time.sleep(0.1)


def _connections_per_worker(svc, workers: dict[int, psutil.Process], n: int) -> list[int]:
    """Open ``n`` keep-alive connections at once, one request each, and count the open
    connections each worker holds."""
    socks = [socket.create_connection(("127.0.0.1", svc.port)) for _ in range(n)]
    try:
        for s in socks:
            s.sendall(b"GET /healthz HTTP/1.1\r\nHost: bdf\r\n\r\n")
        for s in socks:
            assert s.recv(65536).startswith(b"HTTP/1.1 200")
        return [
            sum(
                c.status == psutil.CONN_ESTABLISHED and c.laddr.port == svc.port
                for c in p.net_connections("tcp")
            )
            for p in workers.values()
        ]
    finally:
        for s in socks:
            s.close()


def test_connections_opened_at_once_are_spread_over_the_workers_and_a_restarted_one(live_server):
    # on one socket shared by the workers this failed in two of three runs (the first to wake
    # took all 16); with a socket each the kernel's hash fails it with probability 2^-15
    svc = live_server(args=["--workers", "2"])
    workers = _workers_listening(svc, 2)
    held = _connections_per_worker(svc, workers, 16)
    assert sum(held) == 16 and min(held) >= 1, held
    killed = next(iter(workers.values()))
    killed.kill()
    killed.wait(30)
    workers = _workers_listening(svc, 2)  # uvicorn starts another, with a socket of its own
    assert killed.pid not in workers
    held = _connections_per_worker(svc, workers, 16)
    assert sum(held) == 16 and min(held) >= 1, held
    # a second service on the port is refused, as without SO_REUSEPORT, not let in to share it
    env = {**os.environ, "BDF_DATA_DIR": str(svc.log_path.parent / "other")}
    cmd = [sys.executable, "-m", "clients.cli", "serve", "--port", str(svc.port), "--workers", "2"]
    other = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert other.returncode != 0 and "cannot listen" in other.stderr + other.stdout
    held = _connections_per_worker(svc, workers, 16)
    assert sum(held) == 16 and min(held) >= 1, held


@pytest.fixture
def postgres():
    """(base URL, a fresh schema) on the test server; skipped without one."""
    base = os.environ.get(POSTGRES_ENV)
    if not base:
        pytest.skip(f"PostgreSQL tests need {POSTGRES_ENV} (e.g. postgresql://postgres@127.0.0.1:5432/test)")
    import psycopg

    schema = f"bdf_iso_{uuid.uuid4().hex[:10]}"
    yield base, schema
    with psycopg.connect(base, autocommit=True) as conn:
        conn.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")


def through(base: str, port: int, schema: str) -> str:
    """``base`` with its host and port replaced by 127.0.0.1:``port``."""
    rest = base.split("@", 1)[1].split("/", 1)[1]
    user = base.split("://", 1)[1].split("@", 1)[0]
    return f"postgresql://{user}@127.0.0.1:{port}/{rest}?schema={schema}"


def pg_target(base: str) -> tuple[str, int]:
    host_port = base.split("@", 1)[1].split("/", 1)[0]
    host, _, port = host_port.partition(":")
    return host, int(port or 5432)


def test_a_paused_database_gives_503_within_its_timeout_and_service_resumes(live_server, postgres):
    base, schema = postgres
    proxy = PausableProxy(pg_target(base))
    env = {"BDF_STORE_URL": through(base, proxy.port, schema), "BDF_STORE_TIMEOUT_S": "2"}
    svc = live_server(env=env)
    try:
        with httpx.Client(base_url=svc.url, timeout=30) as http:
            http.post("/v1/regions", json=SPEC).raise_for_status()
            for i in range(3):
                X, V = data(10 + i, n=100)
                post_json(
                    http,
                    "/v1/regions/town/observations",
                    {"points": X.tolist(), "velocities": V.tolist()},
                    headers={"Idempotency-Key": f"u{i}"},
                ).raise_for_status()
            Q = data(2, n=10)[0].tolist()
            post_json(http, "/v1/regions/town/query?min_version=3", {"points": Q}).raise_for_status()
            proxy.pause()
            X, V = data(13, n=100)
            late = {"points": X.tolist(), "velocities": V.tolist()}
            calls = {
                "list": lambda: http.get("/v1/regions"),
                "region": lambda: http.get("/v1/regions/town"),
                "query": lambda: post_json(http, "/v1/regions/town/query", {"points": Q}),
                "grid": lambda: http.get("/v1/regions/town/grid", params={"step": "50"}),
                "tiles": lambda: http.get("/v1/regions/town/tiles"),
                "upload": lambda: post_json(
                    http, "/v1/regions/town/observations", late, headers={"Idempotency-Key": "u3"}
                ),
                "readyz": lambda: http.get("/readyz"),
            }
            for name, call in calls.items():
                t = time.perf_counter()
                r = call()
                took = time.perf_counter() - t
                assert r.status_code == 503, (name, r.text)
                assert took < 2 + 1.5, (name, took)  # the store timeout and the watchdog's tick
                assert int(r.headers["retry-after"]) > 0
                t = time.perf_counter()
                assert http.get("/healthz").status_code == 200 and time.perf_counter() - t < 0.05
            proxy.resume()
            deadline = time.monotonic() + 10
            while http.get("/readyz").status_code != 200:
                assert time.monotonic() < deadline
                time.sleep(0.2)
            r = post_json(http, "/v1/regions/town/observations", late, headers={"Idempotency-Key": "u3"})
            assert r.status_code == 200 and not r.json()["replayed"]  # the paused try stored nothing
            view = http.get("/v1/regions/town").json()
            assert view["version"] == 4 and view["observations"] == 400
            assert post_json(http, "/v1/regions/town/query?min_version=4", {"points": Q}).status_code == 200
    finally:
        proxy.stop()


def test_the_service_starts_with_the_database_down_and_is_ready_when_it_is_back(live_server, postgres):
    base, schema = postgres
    port = free_port()
    svc = live_server(env={"BDF_STORE_URL": through(base, port, schema), "BDF_STORE_TIMEOUT_S": "2"})
    assert httpx.get(f"{svc.url}/healthz", timeout=5).status_code == 200
    r = httpx.get(f"{svc.url}/readyz", timeout=5)
    assert r.status_code == 503 and r.headers["content-type"] == "application/problem+json"
    assert httpx.get(f"{svc.url}/v1/regions", timeout=10).status_code == 503
    log = svc.log()
    assert (
        "Traceback" not in log
        and sum("PostgreSQL cannot be reached" in line for line in log.splitlines()) >= 1
    )
    proxy = PausableProxy(pg_target(base), port=port)
    try:
        deadline = time.monotonic() + 15
        while httpx.get(f"{svc.url}/readyz", timeout=5).status_code != 200:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        assert httpx.post(f"{svc.url}/v1/regions", json=SPEC, timeout=30).status_code == 201
    finally:
        proxy.stop()
