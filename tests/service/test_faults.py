"""Faults of the service's surroundings: the database gone, a read-only or full disk, a
damaged tile, the server killed during an upload storm. Each ends with the stored data
intact and equal to exactly the uploads that were acknowledged."""

import json
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.parse
import uuid

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from bdf.region.evidence import increments
from bdf.region.spec import RegionSpec
from clients.local import LocalService
from service.app import create_app
from service.settings import Settings
from service.store import open_store
from service.store.sqlite import FILE_NAME
from tests.service.conftest import POSTGRES_ENV
from tests.service.test_store import SPEC, assert_evidence_equal, data

pytestmark = pytest.mark.slow  # servers killed, disks full, subprocesses

NAME = SPEC["name"]
OBS = f"/v1/regions/{NAME}/observations"
QUERY = f"/v1/regions/{NAME}/query"


def upload(client, key: str, seed: int, n: int = 100):
    X, V = data(seed, n=n)
    return client.post(
        OBS, json={"points": X.tolist(), "velocities": V.tolist()}, headers={"Idempotency-Key": key}
    )


def assert_stored(store_url: str, seeds: list[int], n: int = 100) -> None:
    """The region holds exactly the uploads of ``seeds``, each once."""
    spec = RegionSpec.model_validate(SPEC)
    store = open_store(store_url)
    try:
        snap = store.snapshot(NAME)
        assert snap.region.observations == n * len(seeds)
        X = np.vstack([data(s, n=n)[0] for s in seeds])
        V = np.vstack([data(s, n=n)[1] for s in seeds])
        assert_evidence_equal(snap.evidence, {k: i.evidence for k, i in increments(spec, X, V).items()})
    finally:
        store.close()


def assert_unavailable(response, status=503):
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/problem+json"
    assert int(response.headers["retry-after"]) > 0
    body = response.json()
    assert body["request_id"] == response.headers["x-request-id"] and "retry" in body["detail"]
    assert "127.0.0.1" not in body["detail"] and "5432" not in body["detail"]  # not where it lives


class Proxy:
    """A TCP proxy to PostgreSQL on a fixed local port that a test can cut (close every
    connection and refuse new ones) and restore."""

    def __init__(self, target: tuple[str, int]):
        self.target = target
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self.restore()

    def restore(self) -> None:
        self._listener = socket.create_server(("127.0.0.1", self.port), reuse_port=False)
        threading.Thread(target=self._accept, args=(self._listener,), daemon=True).start()

    def cut(self) -> None:
        self._listener.shutdown(socket.SHUT_RDWR)  # wakes the accepting thread (close alone does not)
        self._listener.close()
        with self._lock:
            for s in self._sockets:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()
            self._sockets.clear()

    def _accept(self, listener) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return
            server = socket.create_connection(self.target)
            with self._lock:
                self._sockets += [client, server]
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(a, b) -> None:
        try:
            while chunk := a.recv(65536):
                b.sendall(chunk)
        except OSError:
            pass
        finally:
            for s in (a, b):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass


def test_postgres_lost_answers_503_and_service_resumes_without_restart():
    base = os.environ.get(POSTGRES_ENV)
    if not base:
        pytest.skip(f"needs {POSTGRES_ENV}")
    import psycopg

    server = urllib.parse.urlsplit(base)
    proxy = Proxy((server.hostname, server.port or 5432))
    schema = f"bdf_test_{uuid.uuid4().hex[:12]}"
    netloc = f"{server.netloc.rpartition('@')[0]}@127.0.0.1:{proxy.port}".lstrip("@")
    url = server._replace(netloc=netloc).geturl() + f"?schema={schema}"
    try:
        with TestClient(create_app(Settings(store_url=url))) as c:
            assert c.post("/v1/regions", json=SPEC).status_code == 201
            assert upload(c, "a", 1).status_code == 200
            answer = c.post(QUERY, json={"points": [[150, 100, 30]]}).json()

            proxy.cut()
            assert_unavailable(upload(c, "b", 2))
            assert_unavailable(c.post(QUERY, json={"points": [[150, 100, 30]]}))
            assert_unavailable(c.get(f"/v1/regions/{NAME}"))
            assert c.get("/readyz").status_code == 503
            assert c.get("/healthz").json() == {"status": "ok"}

            proxy.restore()
            assert c.get("/readyz").status_code == 200
            assert c.post(QUERY, json={"points": [[150, 100, 30]]}).json() == answer
            retried = upload(c, "b", 2)  # the client's retry with its key applies once
            assert retried.status_code == 200 and not retried.json()["replayed"]
            replay = upload(c, "b", 2)
            assert replay.json().get("replayed"), replay.text
        assert_stored(url, [1, 2])
    finally:
        proxy.cut()
        with psycopg.connect(base, autocommit=True) as conn:
            conn.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")


@pytest.fixture
def small_disk(tmp_path):
    """A tmpfs of 16 MiB mounted for the test (root only; skipped with the reason elsewhere)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(mount)], capture_output=True
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.decode().strip()}): needs root")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def remount(mount, mode: str) -> None:
    subprocess.run(["mount", "-o", f"remount,{mode}", str(mount)], check=True)


def test_sqlite_on_a_read_only_disk_refuses_uploads_and_keeps_serving(small_disk):
    """The disk goes read-only under a stopped server (a busy mount cannot be remounted)
    and the server starts on it."""
    url = f"sqlite:///{small_disk / 'data'}"
    with TestClient(create_app(Settings(store_url=url))) as c:
        assert c.post("/v1/regions", json=SPEC).status_code == 201
        assert upload(c, "a", 1).status_code == 200
        answer = c.post(QUERY, json={"points": [[150, 100, 30]]}).json()
    remount(small_disk, "ro")
    try:
        with TestClient(create_app(Settings(store_url=url))) as c:
            assert_unavailable(upload(c, "b", 2))
            again = c.post(QUERY, json={"points": [[150, 100, 30]]}).json()
            assert again["region_version"] == answer["region_version"] and again["known"] == answer["known"]
            for field in ("mean", "std"):  # this process computed the map again: equal to rounding
                np.testing.assert_allclose(again[field], answer[field], rtol=1e-12)
            assert c.get(f"/v1/regions/{NAME}").json()["version"] == 1
    finally:
        remount(small_disk, "rw")
    with TestClient(create_app(Settings(store_url=url))) as c:
        assert upload(c, "b", 2).json()["replayed"] is False
    assert_stored(url, [1, 2])


def test_sqlite_on_a_full_disk_refuses_uploads_and_recovers_when_space_is_back(small_disk):
    url = f"sqlite:///{small_disk / 'data'}"
    with TestClient(create_app(Settings(store_url=url))) as c:
        assert c.post("/v1/regions", json=SPEC).status_code == 201
        assert upload(c, "a", 1).status_code == 200
        answer = c.post(QUERY, json={"points": [[150, 100, 30]]}).json()
        ballast = small_disk / "ballast"
        with open(ballast, "wb") as f:  # fill the disk to the last block
            try:
                while True:
                    f.write(b"\0" * 65536)
                    f.flush()
            except OSError:
                pass
        assert_unavailable(upload(c, "b", 2), status=507)
        assert c.post(QUERY, json={"points": [[150, 100, 30]]}).json() == answer
        assert c.get(f"/v1/regions/{NAME}").json()["version"] == 1
        ballast.unlink()
        assert upload(c, "b", 2).json()["replayed"] is False
    assert_stored(url, [1, 2])


def damage(store_url: str, tmp_path) -> str:
    """Flip bytes inside one stored tile's statistics, below the store (on disk for
    SQLite); returns the tile's key."""
    store = open_store(store_url)
    snap = store.snapshot(NAME, keys=())
    key = sorted(snap.tiles)[0]
    key_text = "_".join(map(str, key))
    store.close()
    if store_url.startswith("sqlite"):
        import sqlite3

        path = tmp_path / "data" / FILE_NAME
        with sqlite3.connect(path) as conn:
            conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            blob = conn.execute("SELECT stats FROM tiles WHERE key = ?", (key_text,)).fetchone()[0]
        raw = bytearray(path.read_bytes())
        # 64 bytes of the blob found once in the file: 8 values none of which is 0 (the
        # speed histogram and empty cells are runs of zeros), not split across overflow pages
        pieces = (
            blob[i : i + 64]
            for i in range(0, len(blob) - 64, 8)
            if np.all(np.frombuffer(blob[i : i + 64], "<f8") != 0)
        )
        piece = next(p for p in pieces if raw.find(p) > 0 and raw.find(p, raw.find(p) + 1) < 0)
        at = raw.find(piece)
        raw[at : at + 8] = bytes(b ^ 0xFF for b in raw[at : at + 8])
        path.write_bytes(bytes(raw))
    else:
        import psycopg

        base, _, query = store_url.partition("?schema=")
        with psycopg.connect(base, autocommit=True) as conn:
            conn.execute(
                f"UPDATE {query}.tiles SET stats = set_byte(stats, 1000, get_byte(stats, 1000) # 255)"
                " WHERE key = %s",
                (key_text,),
            )
    return key_text


def test_a_damaged_tile_is_reported_by_name_and_never_served(store_url, tmp_path):
    with TestClient(create_app(Settings(store_url=store_url))) as c:
        assert c.post("/v1/regions", json=SPEC).status_code == 201
        assert upload(c, "a", 1, n=400).status_code == 200
    key = damage(store_url, tmp_path)

    with TestClient(create_app(Settings(store_url=store_url))) as c:  # the map stored before the damage
        r = c.post(QUERY, json={"points": [[150, 100, 30]]})
        assert r.status_code == 200 and r.json()["region_version"] == 1
    store = open_store(store_url)
    store.drop_map(store.region(NAME).region_id, 1)  # computed again, from every tile
    store.close()

    with TestClient(create_app(Settings(store_url=store_url)), raise_server_exceptions=False) as c:
        r = c.post(QUERY, json={"points": [[150, 100, 30]]})
        assert r.status_code == 500 and r.headers["content-type"] == "application/problem+json"
        assert f"tile {key} of region {NAME!r}" in r.json()["detail"] and "checksum" in r.json()["detail"]
        assert r.json()["request_id"] == r.headers["x-request-id"]
        r = upload(c, "b", 2, n=400)  # an upload onto the damaged tile is refused whole
        assert r.status_code == 500 and key in r.json()["detail"]
        assert c.get(f"/v1/regions/{NAME}").json()["version"] == 1

    cli = [sys.executable, "-m", "clients.cli", "verify", "--store-url", store_url]
    done = subprocess.run(cli, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and f"tile {key} of region {NAME!r}" in done.stdout, done.stdout
    assert "1 problems" in done.stdout


def test_verify_passes_a_sound_store(store_url):
    with TestClient(create_app(Settings(store_url=store_url))) as c:
        assert c.post("/v1/regions", json=SPEC).status_code == 201
        assert upload(c, "a", 1, n=400).status_code == 200
    cli = [sys.executable, "-m", "clients.cli", "verify", "--store-url", store_url]
    done = subprocess.run(cli, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and f"{NAME}: ok" in done.stdout, done.stdout + done.stderr


def test_server_killed_during_an_upload_storm_applies_every_acknowledged_upload_once(store_url, tmp_path):
    """4 clients send 6 uploads each and retry each with its key until it is acknowledged;
    the server is SIGKILLed after the 5th acknowledgement and restarted on the same port."""
    env = {"BDF_STORE_URL": store_url}
    server = LocalService(tmp_path / "data", env, log_path=tmp_path / "server-0.log")
    port = server.port
    httpx.post(f"{server.url}/v1/regions", json=SPEC, timeout=60).raise_for_status()
    acked, lock = [], threading.Lock()
    enough = threading.Event()

    def client(c: int) -> None:
        with httpx.Client(base_url=server.url, timeout=30) as http:
            for i in range(6):
                seed = 100 * c + i
                deadline = time.monotonic() + 120
                while True:
                    try:
                        r = upload(http, f"c{c}-{i}", seed)
                        if r.status_code == 200:
                            break
                        assert r.status_code >= 500, r.text  # a client error would be a bug
                    except httpx.TransportError:
                        pass
                    assert time.monotonic() < deadline, "no acknowledgement within 120 s"
                    time.sleep(0.2)
                with lock:
                    acked.append(seed)
                    if len(acked) >= 5:
                        enough.set()

    threads = [threading.Thread(target=client, args=(c,)) for c in range(4)]
    for t in threads:
        t.start()
    assert enough.wait(120)
    server.proc.kill()  # SIGKILL: no graceful shutdown
    server.proc.wait(30)
    killed_at = len(acked)
    restarted = LocalService(tmp_path / "data", env, log_path=tmp_path / "server-1.log", port=port)
    try:
        for t in threads:
            t.join(300)
        assert killed_at < 24 and sorted(acked) == sorted(100 * c + i for c in range(4) for i in range(6))
    finally:
        restarted.stop()
    assert_stored(store_url, acked)


def raw_connection(store_url: str):
    """An autocommit connection to the store's own tables, beside the store (what an older
    version left), and its parameter mark."""
    if store_url.startswith("sqlite"):
        import sqlite3

        path = store_url.removeprefix("sqlite:///") + f"/{FILE_NAME}"
        return sqlite3.connect(path, isolation_level=None), "?"
    import psycopg

    base, _, schema = store_url.partition("?schema=")
    return psycopg.connect(base, autocommit=True, options=f"-c search_path={schema}"), "%s"


def test_a_schema_2_store_is_upgraded_with_checksums_and_loses_nothing(store_url):
    with TestClient(create_app(Settings(store_url=store_url))) as c:
        assert c.post("/v1/regions", json=SPEC).status_code == 201
        assert upload(c, "a", 1).status_code == 200
    conn, _ = raw_connection(store_url)
    conn.execute("ALTER TABLE tiles DROP COLUMN checksum")
    conn.execute("UPDATE meta SET value = '2' WHERE key = 'schema_version'")
    conn.close()

    store = open_store(store_url)
    try:
        assert store.verify() == {NAME: []}
    finally:
        store.close()
    assert_stored(store_url, [1])


@pytest.mark.parametrize("stored_without", [("model_directions",), ("model_directions", "directions")])
def test_a_schema_5_store_keeps_its_one_class_regions_on_the_model_their_evidence_holds(
    store_url, stored_without
):
    """Schema 6 writes out a region's model sectors: a region of one class stored before it
    holds one class's evidence, which a new spec's defaults (8 sectors; "auto" directions,
    for a spec stored before ``directions`` existed) would not read."""
    paper = {**SPEC, "model_directions": 1}
    with TestClient(create_app(Settings(store_url=store_url))) as c:
        assert c.post("/v1/regions", json=paper).status_code == 201
        assert upload(c, "a", 1).status_code == 200
        before = c.post(QUERY, json={"points": data(2, n=20)[0].tolist()}).json()
        assert len(before["mean"]) == 20
    conn, mark = raw_connection(store_url)
    (text,) = conn.execute("SELECT spec FROM regions").fetchone()
    old = json.loads(text)
    for field in stored_without:  # as schema 5 (or a store before directions) stored it
        del old[field]
    conn.execute(f"UPDATE regions SET spec = {mark}", (json.dumps(old),))
    conn.execute("UPDATE meta SET value = '5' WHERE key = 'schema_version'")
    conn.close()

    store = open_store(store_url)
    try:
        assert store.verify() == {NAME: []}
        snap = store.snapshot(NAME)
        assert snap.region.spec == RegionSpec.model_validate(paper)
        X, V = data(1, n=100)  # upload "a"
        expected = increments(snap.region.spec, X, V)
        assert_evidence_equal(snap.evidence, {k: i.evidence for k, i in expected.items()})
    finally:
        store.close()
    with TestClient(create_app(Settings(store_url=store_url))) as c:
        after = c.post(QUERY, json={"points": data(2, n=20)[0].tolist()}).json()
        assert (after["mean"], after["std"], after["known"]) == (
            before["mean"],
            before["std"],
            before["known"],
        )


def test_the_posterior_process_leaves_when_its_worker_is_killed(tmp_path):
    """A service worker killed (SIGKILL, out of memory) cannot stop its posterior process,
    which would wait for work forever: it exits by itself once its parent is gone."""
    import psutil

    script = f"""
import time
from bdf.region.evidence import region_total
from bdf.region.spec import RegionSpec
from service.maps import RegionMaps
from service.store import open_store
from tests.service.test_store import SPEC
store = open_store("sqlite:///{tmp_path}/maps.db")
spec = RegionSpec.model_validate(SPEC)
maps = RegionMaps(store, isolate=True)
maps.refresher.posterior(spec, region_total(spec, {{}}))
print(*maps.refresher._pool._processes, flush=True)
time.sleep(600)
"""
    worker = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=os.getcwd()
    )
    try:
        child = psutil.Process(int(worker.stdout.readline()))
        assert child.ppid() == worker.pid and child.is_running()
    finally:
        worker.kill()
        worker.wait()
        worker.stdout.close()
    gone, alive = psutil.wait_procs([child], timeout=30)
    assert gone and not alive


def test_a_damaged_stored_map_is_reported_and_computed_again(store_url):
    """A stored map is derived data: damaged, `bdf verify` names it, and the next process
    computes the map again from the tiles (the same answer) and stores it over."""
    with TestClient(create_app(Settings(store_url=store_url))) as c:
        assert c.post("/v1/regions", json=SPEC).status_code == 201
        assert upload(c, "a", 1, n=400).status_code == 200
        assert c.post(f"/v1/regions/{NAME}/hyperparameters").status_code == 200  # settled
        first = c.post(QUERY, json={"points": [[150, 100, 30]]}).json()
    store = open_store(store_url)
    region_id = store.region(NAME).region_id
    with store._write() as q:  # one byte of the stored posterior flipped
        (blob,) = q("SELECT posterior FROM maps WHERE region_id = ?", (region_id,))[0]
        blob = bytearray(blob)
        blob[len(blob) // 2] ^= 0xFF
        q("UPDATE maps SET posterior = ? WHERE region_id = ?", (bytes(blob), region_id))
    problems = store.verify()[NAME]
    assert len(problems) == 1 and "stored map of version 1 fails its checksum" in problems[0], problems
    store.close()

    app = create_app(Settings(store_url=store_url))
    with TestClient(app) as c:
        assert c.post(f"/v1/regions/{NAME}/hyperparameters").status_code == 200
        again = c.post(QUERY, json={"points": [[150, 100, 30]]}).json()
        assert app.state.service.maps.stats.count >= 1 and app.state.service.maps.stats.loaded == 0
    assert again["region_version"] == 1
    np.testing.assert_allclose(again["mean"], first["mean"], rtol=1e-9)
    store = open_store(store_url)
    assert store.verify() == {NAME: []}
    store.close()
