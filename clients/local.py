"""A service on this machine for demos, benchmarks and tests: ``bdf serve`` in a subprocess
on 127.0.0.1, started on a free port, ready when it returns, stopped with SIGTERM."""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

#: where Linux picks the local ports of outgoing connections (the default if unreadable)
EPHEMERAL = Path("/proc/sys/net/ipv4/ip_local_port_range")


def free_port() -> int:
    """A free port on 127.0.0.1 below the ephemeral range. A port inside it can be taken
    while the service is down (a restart) by a client connecting to it: a loopback
    connection to a port nothing listens on may get that very port as its own (TCP
    simultaneous open), and the restarted server's bind then fails with "address already
    in use". Ports a service listens on belong outside the range (8000, the default, is)."""
    try:
        low = int(EPHEMERAL.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    rng = random.Random()
    for _ in range(200):
        port = rng.randrange(max(low // 2, 1024), low)
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port found below the ephemeral range ({low})")


class LocalService:
    """``with LocalService(data_dir) as svc: httpx.get(svc.url + "/healthz")``.

    ``env``: extra ``BDF_*`` settings; the caller's ``BDF_*`` variables are not inherited,
    so the service sees exactly what is asked for. The log goes to ``log_path``.
    """

    def __init__(
        self,
        data_dir,
        env: dict | None = None,
        args=(),
        log_path=None,
        start_timeout_s: float = 60,
        port: int | None = None,
    ):
        """``port``: where to listen (default: a free one, :func:`free_port`), e.g. a
        restart's old port."""
        data_dir = Path(data_dir)
        self.port = free_port() if port is None else port
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = Path(log_path or data_dir / f"server-{self.port}.log")
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        full_env = {k: v for k, v in os.environ.items() if not k.startswith("BDF_")}
        full_env.update({"BDF_DATA_DIR": str(data_dir), **(env or {})})
        cmd = [sys.executable, "-m", "clients.cli", "serve", "--port", str(self.port), *args]
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(cmd, env=full_env, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + start_timeout_s
        while not self._healthy():
            if self.proc.poll() is not None:
                raise RuntimeError(f"the service exited ({self.proc.returncode}):\n{self.log()}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"the service did not start within {start_timeout_s} s:\n{self.log()}")
            time.sleep(0.1)

    def _healthy(self) -> bool:
        try:
            return httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200
        except httpx.TransportError:
            return False

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, timeout_s: float = 60) -> int:
        """SIGTERM (graceful: requests in flight finish), then SIGKILL after ``timeout_s``."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    def __enter__(self) -> LocalService:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
