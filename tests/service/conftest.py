import os
import uuid

import pytest

from service.store import open_store

#: CI sets this (see .ci/run); elsewhere the PostgreSQL half of the store suite is skipped.
POSTGRES_ENV = "BDF_TEST_POSTGRES_URL"


@pytest.fixture(params=["sqlite", "postgres"])
def store_url(request, tmp_path):
    """A fresh, empty store of each backend, as a URL (processes open their own)."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'data'}"
        return
    base = os.environ.get(POSTGRES_ENV)
    if not base:
        pytest.skip(f"PostgreSQL tests need {POSTGRES_ENV} (e.g. postgresql://postgres@127.0.0.1:5432/test)")
    import psycopg

    schema = f"bdf_test_{uuid.uuid4().hex[:12]}"
    yield f"{base}?schema={schema}"
    with psycopg.connect(base, autocommit=True) as conn:
        conn.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")


@pytest.fixture
def store(store_url):
    s = open_store(store_url)
    yield s
    s.close()


class LiveServer:
    """``bdf serve`` in a subprocess on 127.0.0.1 (a real uvicorn), its log in a file."""

    def __init__(self, tmp_path, env: dict, args=()):
        import socket
        import subprocess
        import sys
        import time

        import httpx

        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            self.port = sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = tmp_path / f"server-{self.port}.log"
        full_env = {k: v for k, v in os.environ.items() if not k.startswith("BDF_")}
        full_env.update({"BDF_DATA_DIR": str(tmp_path / "data"), "BDF_LOG_LEVEL": "info", **env})
        cmd = [sys.executable, "-m", "clients.cli", "serve", "--port", str(self.port), *args]
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(cmd, env=full_env, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 30
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the server exited ({self.proc.returncode}):\n{self.log()}")
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"the server did not start:\n{self.log()}")
            time.sleep(0.1)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self) -> int:
        import signal
        import subprocess

        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


@pytest.fixture
def live_server(tmp_path):
    """A factory: ``live_server(env={...}, args=[...])`` starts a server, stopped at teardown."""
    servers = []

    def start(env=None, args=()):
        servers.append(LiveServer(tmp_path, env or {}, args))
        return servers[-1]

    yield start
    for server in servers:
        server.stop()
