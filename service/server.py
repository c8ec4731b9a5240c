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
  request at once, keep being served while half-open ones come and go.

A body that trickles in without pausing that long is bounded by the request deadline
(:mod:`service.lanes`).
"""

from __future__ import annotations

import functools
import logging
import resource

import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.settings import Settings

log = logging.getLogger("bdf.service")
#: descriptors kept beside client connections: the store, the posterior process, logs
SPARE_FDS = 256


@functools.cache
def _limits() -> tuple[float, int]:
    """(header_timeout_s, max_connections) of this worker's settings (a worker process
    builds its settings from the environment, as the app does)."""
    settings = Settings()
    return settings.header_timeout_s, connection_cap(settings.max_connections)


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

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._await_request()
        _, cap = _limits()
        if len(self.connections) > cap:
            self._shed()

    def on_headers_complete(self) -> None:
        super().on_headers_complete()
        self._in_body = True
        self._arm()  # a body, if any, must keep arriving

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._in_body and self._timer is not None:
            self._arm()  # each read of the body restarts its clock; headers have one in all

    def on_message_complete(self) -> None:
        self._in_body = False
        self._cancel()
        super().on_message_complete()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._await_request()

    def connection_lost(self, exc) -> None:
        self._cancel()
        super().connection_lost(exc)

    def _await_request(self) -> None:
        self._since, self._in_body = self.loop.time(), False
        self._arm()

    def _arm(self) -> None:
        self._cancel()
        timeout, _ = _limits()
        self._timer = self.loop.call_later(timeout, self._late)

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


def run(settings: Settings) -> None:
    """Serve the app with ``settings`` (the workers rebuild them from the environment)."""
    connection_cap(settings.max_connections)  # raise the descriptor limit before the workers start
    uvicorn.run(
        "service.app:create_app",
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
