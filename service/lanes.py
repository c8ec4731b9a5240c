"""Lanes and deadlines: one kind of work never starves another, and no request runs forever.

Work runs in two lanes of threads, each with bounded capacity: *light* (region reads, small
queries, grids and uploads on a map that is ready) and *heavy* (fits, large queries, grids
and uploads, and whatever must wait for a map being computed). A burst of heavy requests
fills only the heavy lane, so small queries keep their threads. A lane holds at most
``threads`` requests at work and ``queue`` waiting; one more is shed at once (503 with
``Retry-After``), never queued without bound. A light step that finds its work heavy hands
it on (:class:`Heavy`).

A step that must wait for a map being computed hands the wait to a third bound,
``waiting`` (threads that block without CPU, many of them), and steps again when the map
is ready: a burst of readers of a new region does not fill the heavy lane with waits.

Where reads never wait on a network or on a writer (a local store: SQLite's WAL), a light
step that only reads a small body (:data:`INLINE_BODY_BYTES`) runs on the event loop itself
(:attr:`Lanes.inline`), in its turn: on these machines handing a step to a thread and back
costs more CPU than a small query's work (the thread and the event loop take the GIL from
each other a dozen times per step: ``bench/history/lane-handoff.py``). Work longer than a
few milliseconds it hands on to a light thread (:class:`Threaded`, :func:`on_loop`), so the
loop is never held long. The loop is then the light lane's one thread: beyond ``threads +
queue`` requests being answered in the process (:func:`received`), a light read is shed at
once as a full lane's. Writes, heavy work and waits keep their threads; so does every light
step on a networked store, whose reads may hang.

Uploads and retractions run one at a time per process, and wait for their turn before
they take a thread at work: the store takes one writer at a time anyway, and each rewrites
the tiles it touches whole (seconds on a 16-sector map, however small its body). A fit
(heavy) does not wait its turn: its map is computed before its one write, and uploads would
wait that computation out.
Two small uploads in the light lane held both its threads, one writing and one waiting for
the store's lock, while queries queued behind them (``bench/bench_service.py --directions
8,16``: no query answered in 6 s).

Every request has a deadline (:func:`deadline`, set once per request by
:class:`service.telemetry.RequestMiddleware`). Waiting for a lane or a map, and every long
loop's checkpoint (:func:`check`), raises :class:`DeadlineExceeded` (503) past it, so the
work stops where it can. The client has its answer at the deadline even while a thread
finishes a step that cannot stop; that thread keeps its lane slot until it ends, so the
lane's bound holds for threads, not only for requests.
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from collections.abc import Callable
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any

import anyio
import anyio.to_thread

#: the niceness of the lanes' threads (Linux: per thread): above the event loop's and the
#: map process's, so that health answers and refreshes keep up while requests fill the cores
NICE = 5
_niced = threading.local()

#: time.monotonic() by which the current request must be answered
_deadline: ContextVar[float] = ContextVar("deadline", default=math.inf)
#: whether the current request's client has left (:func:`client`; never, unless told)
_client_gone: ContextVar[Callable[[], bool]] = ContextVar("client_gone", default=lambda: False)
#: A light read whose request body is larger runs in a thread: decoding it would hold the
#: event loop (a 1,000-point Arrow query is 24 KB; JSON about 60)
INLINE_BODY_BYTES = 64 * 1024
_inline = threading.local()  # .active: the event loop's thread is running a read (Lane.inline)
#: requests this process has received (their headers) and not yet answered, counted by the
#: server's protocol (:mod:`service.server`) on the event loop: no lock
_answering = 0


class Overloaded(Exception):
    """A lane is full: the client should retry after ``retry_after_s``."""

    def __init__(self, detail: str, retry_after_s: int):
        super().__init__(detail)
        self.retry_after_s = retry_after_s


class DeadlineExceeded(Exception):
    """The request's deadline passed before its work ended (a write's before its commit)."""


@contextlib.contextmanager
def deadline(seconds: float):
    """Within this block, the current context's work must end within ``seconds`` (or an
    earlier deadline already set)."""
    token = _deadline.set(min(_deadline.get(), time.monotonic() + seconds))
    try:
        yield
    finally:
        _deadline.reset(token)


def received() -> None:
    """A request's headers have arrived: it waits for the event loop, or is at work."""
    global _answering
    _answering += 1


def answered() -> None:
    """... and its answer is sent (or its connection lost): what an inline read is shed
    beyond (:meth:`Lane.inline`)."""
    global _answering
    _answering -= 1


@contextlib.contextmanager
def client(gone: Callable[[], bool]):
    """Within this block, ``gone()`` tells whether the current request's client has left: an
    inline read whose client left while it waited for its turn is dropped, not computed."""
    token = _client_gone.set(gone)
    try:
        yield
    finally:
        _client_gone.reset(token)


def on_loop() -> bool:
    """This is a light read running on the event loop: long work should be :class:`Threaded`."""
    return getattr(_inline, "active", False)


def remaining() -> float:
    """Seconds left before the current deadline (inf without one)."""
    return _deadline.get() - time.monotonic()


def check() -> None:
    """A checkpoint of long work: :class:`DeadlineExceeded` once the deadline has passed."""
    if remaining() <= 0:
        raise DeadlineExceeded(
            "the request's deadline passed before its work ended, which stopped there (a write "
            "stops before its commit: nothing was stored)"
        )


def wait_timeout() -> float | None:
    """A blocking wait's timeout: what is left of the deadline (None: no deadline)."""
    left = remaining()
    return None if left == math.inf else max(left, 0.0)


@dataclass(frozen=True)
class Heavy:
    """What a light step returns when the rest of its work belongs in the heavy lane."""

    work: Callable[[], Any]


@dataclass(frozen=True)
class Threaded:
    """What a light step on the event loop returns when the rest of its work would hold the
    loop too long (:func:`on_loop`): it goes on in a light lane's thread."""

    work: Callable[[], Any]


@dataclass(frozen=True)
class Waiting:
    """What a light step returns when it must wait (for a map being computed) before it
    can go on: ``wait()`` blocks without using the CPU, then ``then()`` is the light step
    again."""

    wait: Callable[[], Any]
    then: Callable[[], Any]


@dataclass
class LaneStats:
    admitted: int = 0  # requests in the lane now: at work or waiting for a thread
    busy: int = 0  # threads at work now (abandoned ones included, until they end)
    shed: int = 0  # requests refused because the lane was full
    expired: int = 0  # requests whose deadline passed while waiting for a thread


class Lane:
    """``threads`` at work at once, at most ``queue`` more waiting; beyond that, shed."""

    def __init__(self, name: str, threads: int, queue: int, retry_after_s: int = 1):
        self.name, self.threads, self.queue, self.retry_after_s = name, threads, queue, retry_after_s
        self.stats = LaneStats()
        self._slots = threading.Semaphore(threads)
        self._lock = threading.Lock()
        # anyio's own bound only lets every admitted request have a thread to wait in
        self._limiter = anyio.CapacityLimiter(threads + queue)

    async def run(self, fn: Callable[[], Any], gate: threading.Semaphore | None = None) -> Any:
        """``fn()`` in one of the lane's threads: :class:`Overloaded` at once if the lane is
        full, :class:`DeadlineExceeded` if the deadline passes first. With ``gate``, the
        request holds it before it takes a thread at work (and waits for it as in the queue)."""
        with self._lock:
            if self.stats.admitted >= self.threads + self.queue:
                raise self._shed()
            self.stats.admitted += 1
        state = {"started": False, "dropped": False}

        def work():
            _lower_priority()
            with self._lock:
                if state["dropped"]:  # the request left before this thread started
                    return None
                state["started"] = True
            try:
                with self._held(gate, "its turn to write"), self._held(self._slots, f"a {self.name} thread"):
                    with self._lock:
                        self.stats.busy += 1
                    try:
                        check()
                        return fn()
                    finally:
                        with self._lock:
                            self.stats.busy -= 1
            finally:
                with self._lock:
                    self.stats.admitted -= 1

        try:
            return await anyio.to_thread.run_sync(work, limiter=self._limiter, abandon_on_cancel=True)
        except anyio.get_cancelled_exc_class():
            with self._lock:
                if not state["started"]:
                    state["dropped"] = True
                    self.stats.admitted -= 1
            raise

    def inline(self, fn: Callable[[], Any]) -> Any:
        """``fn()`` here, in the event loop's thread, counted as the lane's work (module doc):
        :class:`Overloaded` at once if the process is answering more requests than the lane
        holds (the loop is its one thread: the rest wait their turn) or the client has left
        (:func:`client`), :class:`DeadlineExceeded` if the deadline has passed already."""
        with self._lock:
            if _answering > self.threads + self.queue or _client_gone.get()():
                raise self._shed()
            self.stats.admitted += 1
            self.stats.busy += 1
        _inline.active = True
        try:
            check()
            return fn()
        finally:
            _inline.active = False
            with self._lock:
                self.stats.busy -= 1
                self.stats.admitted -= 1

    def _shed(self) -> Overloaded:
        """A request refused at once (counted), holding :attr:`_lock`."""
        self.stats.shed += 1
        return Overloaded(
            f"the service is at capacity for {self.name} work; retry in {self.retry_after_s} s",
            self.retry_after_s,
        )

    @contextlib.contextmanager
    def _held(self, semaphore: threading.Semaphore | None, waited_for: str):
        """``semaphore`` held (None: nothing to hold) until the block ends;
        :class:`DeadlineExceeded` (counted expired) if the request's deadline passes first."""
        if semaphore is None:
            yield
            return
        if not semaphore.acquire(timeout=wait_timeout()):
            with self._lock:
                self.stats.expired += 1
            raise DeadlineExceeded(
                f"the request's deadline passed while it waited for {waited_for}; nothing was done"
            )
        try:
            yield
        finally:
            semaphore.release()


def _lower_priority() -> None:
    """This thread at :data:`NICE`, once (where the system allows a thread its own)."""
    if getattr(_niced, "done", False):
        return
    _niced.done = True
    with contextlib.suppress(OSError, AttributeError):
        current = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), max(current, NICE))


class Lanes:
    """The light and the heavy lane, the waiters, and the writes (module doc)."""

    def __init__(
        self,
        light_threads: int,
        light_queue: int,
        heavy_threads: int,
        heavy_queue: int,
        waiters: int = 64,
        inline: bool = False,
    ):
        """``inline``: light steps that only read run on the event loop (module doc)."""
        self.inline = inline
        self.light = Lane("light", light_threads, light_queue)
        self.heavy = Lane("heavy", heavy_threads, heavy_queue, retry_after_s=5)
        # a wait for a map takes a thread but no CPU: many may wait, each until its deadline
        self.waiting = Lane("waiting", waiters, 0, retry_after_s=5)
        self.writes = threading.Semaphore(1)

    async def run(
        self, fn: Callable[[], Any], heavy: bool = False, write: bool = False, body_bytes: int = 0
    ) -> Any:
        """``fn()`` in the light lane (the heavy one if ``heavy``; on the event loop if it
        only reads, its request's body is at most :data:`INLINE_BODY_BYTES` and
        :attr:`inline`), one ``write`` at a time; a :class:`Heavy` it returns runs on in the
        heavy lane, a :class:`Threaded` in a light thread, a :class:`Waiting` waits, then
        steps again."""
        loop = self.inline and not (heavy or write) and body_bytes <= INLINE_BODY_BYTES
        if loop:
            result = self.light.inline(fn)
        else:
            result = await (self.heavy if heavy else self.light).run(fn, self.writes if write else None)
        while isinstance(result, Heavy | Threaded | Waiting):
            if isinstance(result, Heavy):
                result = await self.heavy.run(result.work)
            elif isinstance(result, Threaded):
                result = await self.light.run(result.work)
            else:
                await self.waiting.run(result.wait)
                result = self.light.inline(result.then) if loop else await self.light.run(result.then)
        return result
