"""The HTTP server: uvicorn, with the connection limits it lacks and logging in every worker.

uvicorn closes idle keep-alive connections (``keep_alive_s``) but never one whose request
line and headers trickle in, and it accepts connections without bound (its
``limit_concurrency`` answers 503 but keeps the socket), so half-open clients can hold every
file descriptor. :class:`GuardedProtocol` (its HTTP protocol, subclassed at its public
asyncio callbacks and its documented parser callbacks) adds:

- a header deadline: a request's line and headers must arrive within ``header_timeout_s``
  of the connection (or the previous response), else the connection closes; a body must
  not pause longer than that between two reads either;
- a connection cap (``max_connections`` per worker): one more connection drops the one that
  has waited longest on its client (for headers, or for a body still arriving), or itself
  when every other connection's request is at work. Authorised clients, which send their
  request at once, keep being served while half-open ones come and go;
- header limits: a request's line and headers are counted as they arrive, before the
  parser sees them, and past ``max_header_kb`` (or ``max_headers`` fields, counted when they
  end) the client gets 431 and the connection closes; the parser (which joins a header's
  pieces by copying them) never holds more, so huge headers cannot stall the event loop.

A request pipelined behind another is at work once its headers are in: the header deadline
is not armed again for it when the first answer is sent.

A body that trickles in without pausing that long is bounded by the request deadline
(:mod:`service.lanes`).

Several workers on Linux listen on a socket each (:class:`WorkerSockets`), so that the
kernel spreads connections over them.
"""

from __future__ import annotations

import functools
import json
import logging
import resource
import socket
import sys
from dataclasses import dataclass

import uvicorn
from uvicorn.config import STARTUP_FAILURE
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.supervisors import Multiprocess

from service import lanes
from service.settings import Settings

log = logging.getLogger("bdf.service")
#: descriptors kept beside client connections: the store, the posterior process, logs
SPARE_FDS = 256
APP = "service.app:create_app"


@dataclass(frozen=True)
class Limits:
    header_timeout_s: float
    max_connections: int
    max_header_bytes: int
    max_headers: int


@functools.cache
def _limits() -> Limits:
    """The connection limits of this worker's settings (a worker process builds its
    settings from the environment, as the app does)."""
    settings = Settings()
    return Limits(
        settings.header_timeout_s,
        connection_cap(settings.max_connections),
        int(settings.max_header_kb * 1024),
        settings.max_headers,
    )


def connection_cap(wanted: int) -> int:
    """``wanted``, or fewer if this process may not open that many descriptors (the soft
    limit is raised to the hard one first)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = wanted + SPARE_FDS
    if soft != resource.RLIM_INFINITY and soft < need:
        soft = need if hard == resource.RLIM_INFINITY else min(hard, need)
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    if soft != resource.RLIM_INFINITY and soft < need:
        log.warning(
            "max_connections %d lowered to %d: %d file descriptors allowed", wanted, soft - SPARE_FDS, soft
        )
        return max(soft - SPARE_FDS, 1)
    return wanted


class GuardedProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with a header deadline and a connection cap (module doc)."""

    _since: float | None = None  # when it began waiting for its current request
    _timer = None  # armed while it waits on its client: for headers, or for a body's next bytes
    _in_body = False  # the headers came; the body is still arriving
    _head_bytes = 0  # of the request line and headers now arriving
    _tail = b""  # the last bytes of them, where their end may begin
    _refused = False  # answered 431: nothing more is read
    _at_work = 0  # its requests whose headers came, not yet answered (service.lanes.received)

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._await_request()
        if len(self.connections) > _limits().max_connections:
            self._shed()

    def on_headers_complete(self) -> None:
        if len(self.headers) > _limits().max_headers:
            return self._refuse(f"more than {_limits().max_headers} header fields")
        super().on_headers_complete()
        self._at_work += 1
        lanes.received()
        self._in_body = True
        self._arm()  # a body, if any, must keep arriving

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return
        if not self._in_body and self._counted(data) > _limits().max_header_bytes:
            return self._refuse(f"a request line and headers longer than {_limits().max_header_bytes} bytes")
        super().data_received(data)
        if self._in_body and self._timer is not None:
            self._arm()  # each read of the body restarts its clock; headers have one in all

    def on_body(self, body: bytes) -> None:
        if not self._refused:
            super().on_body(body)

    def on_message_complete(self) -> None:
        if self._refused:
            return
        self._in_body, self._head_bytes, self._tail = False, 0, b""  # the next request's head
        self._cancel()
        super().on_message_complete()

    def on_response_complete(self) -> None:
        pipelined = bool(self.pipeline)  # its headers are in: it is at work, not awaited
        if self._at_work:
            self._at_work -= 1
            lanes.answered()
        super().on_response_complete()
        if not (pipelined or self.transport.is_closing()):
            self._await_request()

    def _counted(self, data: bytes) -> int:
        """The bytes of the request's line and headers so far, with those of ``data`` (up to
        the blank line that ends them, if it is in ``data``)."""
        seen = self._tail + data
        end = seen.find(b"\r\n\r\n")
        self._head_bytes += len(data) if end < 0 else max(end + 4 - len(self._tail), 0)
        self._tail = seen[-3:]
        return self._head_bytes

    def _refuse(self, what: str) -> None:
        """431 (problem+json) and close: the request's headers are over a limit."""
        self._refused = True
        self._cancel()
        body = json.dumps(
            {
                "type": "about:blank",
                "title": "Request Header Fields Too Large",
                "status": 431,
                "detail": f"{what}: send fewer or shorter headers",
            }
        ).encode()
        head = (
            "HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-type: application/problem+json\r\n"
            f"content-length: {len(body)}\r\nconnection: close\r\n\r\n"
        )
        self.transport.write(head.encode() + body)
        self.transport.close()

    def connection_lost(self, exc) -> None:
        self._cancel()
        for _ in range(self._at_work):  # never to be answered
            lanes.answered()
        self._at_work = 0
        super().connection_lost(exc)

    def _await_request(self) -> None:
        # not the end of a body: an answer sent before its request's body ended (a 413 at
        # its length) leaves the rest of the body to arrive, and it is body, not headers
        self._since = self.loop.time()
        self._arm()

    def _arm(self) -> None:
        self._cancel()
        self._timer = self.loop.call_later(_limits().header_timeout_s, self._late)

    def _cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _late(self) -> None:
        """The client sent no headers, or paused its body, for ``header_timeout_s``."""
        self._timer = None
        if not self.transport.is_closing():
            self.transport.close()

    def _waits_on_client(self) -> bool:
        """No request at work: headers still to come, or a body still arriving."""
        return self._timer is not None and not self.transport.is_closing()

    def _shed(self) -> None:
        waiting = [c for c in self.connections if isinstance(c, GuardedProtocol) and c._waits_on_client()]
        others = [c for c in waiting if c is not self]
        victim = min(others, key=lambda c: c._since) if others else self
        victim.transport.close()


def log_config(level: str) -> dict:
    """uvicorn's logging plus ours (the access lines, the service's), applied in every
    worker process."""
    config = {**uvicorn.config.LOGGING_CONFIG}
    config["formatters"] = {**config["formatters"], "bdf": {"format": "%(message)s"}}
    config["handlers"] = {
        **config["handlers"],
        "bdf": {"class": "logging.StreamHandler", "formatter": "bdf", "stream": "ext://sys.stderr"},
    }
    config["loggers"] = {
        **config["loggers"],
        "bdf": {"handlers": ["bdf"], "level": level.upper(), "propagate": False},
        "service": {"handlers": ["bdf"], "level": level.upper(), "propagate": False},
    }
    return config


class WorkerSockets(list):
    """The listening socket of a worker process: its own, bound with ``SO_REUSEPORT``, made
    where this list is unpickled (uvicorn sends its sockets to each worker it spawns, and
    again to each it restarts).

    On one socket shared by all workers, the first worker to wake takes every connection
    waiting, and keep-alive clients stay where they landed: under 16 connections opened at
    once one of two workers served them all while the other idled at 0.001 of a core
    (``bench/bench_query_cpu.py``, ``bench/RESULTS.md`` 2026-11-29). With a socket each, the
    kernel spreads connections over the workers by a hash of their addresses. The parent
    holds the port with a socket bound the same way that never listens, so no connection
    waits on it."""

    def __init__(self, family: int, address: tuple, held: socket.socket | None = None):
        super().__init__([held if held is not None else reuse_port_socket(family, address)])
        self.family, self.address = family, address

    def __reduce__(self):
        return WorkerSockets, (self.family, self.address)


def reuse_port_socket(family: int, address: tuple) -> socket.socket:
    """A TCP socket bound to ``address`` with ``SO_REUSEPORT`` (and uvicorn's ``SO_REUSEADDR``)."""
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    sock.bind(address)
    return sock


def _held_port(family: int, address: tuple) -> socket.socket:
    """The parent's socket that holds the port for the workers' (:class:`WorkerSockets`):
    bound with ``SO_REUSEPORT`` once a bind without it succeeded, so that a port in use
    fails as it would without, another ``bdf serve`` on it too (whose sockets would
    otherwise share its connections with ours)."""
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind(address)
        port = probe.getsockname()[1]  # the one the system chose for port 0
    return reuse_port_socket(family, (address[0], port))


def run(settings: Settings) -> None:
    """Serve the app with ``settings`` (the workers rebuild them from the environment);
    several workers on Linux listen on a socket each (:class:`WorkerSockets`)."""
    connection_cap(settings.max_connections)  # raise the descriptor limit before the workers start
    options = dict(
        factory=True,
        host=settings.host,
        port=settings.port,
        workers=settings.workers,
        http=GuardedProtocol,
        timeout_keep_alive=settings.keep_alive_s,
        access_log=False,  # one structured line per request comes from the app
        log_config=log_config(settings.log_level),
        log_level=settings.log_level,
        timeout_graceful_shutdown=60,
    )
    if settings.workers == 1 or sys.platform != "linux":
        uvicorn.run(APP, **options)
        return
    config = uvicorn.Config(APP, **options)
    family = socket.AF_INET6 if ":" in settings.host else socket.AF_INET
    try:
        held = _held_port(family, (settings.host, settings.port))
    except OSError as exc:
        log.error("cannot listen on %s:%d: %s", settings.host, settings.port, exc)
        sys.exit(STARTUP_FAILURE)
    address = held.getsockname()[:2]
    log.info("listening on %s:%d, a socket per worker", *address)
    Multiprocess(config, sockets=WorkerSockets(family, address, held)).run()
