"""Region maps computed once, in the background: the refreshes, the stored maps and the
posterior process.

The store holds the truth (tile statistics, versions, ledger); a region's map is derived
data: the posterior of the sum of its tiles' evidence at the spec's hyperparameters
("auto": the evidence maximum of that version's data, whatever uploads brought it), per
``(region_id, version)``, kept in a memory-bounded LRU (:class:`PosteriorCache`).

Refreshes: a write answers at once and schedules its region's refresh. One refresh per
region runs at a time, always of the newest version (versions written meanwhile are
skipped, not queued: the next refresh starts from the newest), warm from the last (the
tiles' decoded evidence whose version has not changed, the previous optimum as the
search's start, the symbolic analysis of an unchanged support in the posterior process).
Its "auto" hyperparameters may stop within a nat of the evidence maximum (the map is fresh
sooner); when no newer version waits, the refresh computes the map again, settled.

Once for every process: each region's newest map is stored beside its evidence
(:meth:`service.store.MapStore.save_map`). A refresh first looks there and loads a map of
its version if one is stored; else it takes the region's lease in the store
(:meth:`~service.store.MapStore.take_lease`, renewed while it computes), computes the map,
stores it and frees the lease. A refresh that finds the lease held waits for the holder's
map, and takes the lease over once it expires (a killed holder: within :data:`LEASE_S`).
So workers, replicas and restarts compute each version's map once, and a restart serves
at once. Readers never compute: they wait for refreshes (:meth:`Refresher.wait`), until
their deadline, and are then told which version is computed since when (:meth:`Refresher.not_ready`).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import itertools
import logging
import math
import multiprocessing
import os
import queue
import socket
import threading
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from bdf import hyperparameters
from bdf.posterior import Mixture, Posterior
from bdf.region.evidence import region_total
from bdf.region.map import RegionMap, compute_posterior, decode_posterior, encode_posterior
from bdf.region.resolution import Choice, choose_directions
from bdf.region.spec import RegionSpec
from service import lanes
from service.store import CorruptTile, MapStore, RegionChanged, RegionInfo, RegionNotFound, StoreUnavailable

log = logging.getLogger(__name__)

#: How long a refresh lease lasts unless renewed (s): a killed holder's work is taken over
#: after at most this long. Its holder renews it every third of it.
LEASE_S = 30.0
#: How often a refresh waiting for another process's map looks for it in the store (s).
LEASE_POLL_S = 0.25
#: A read waiting for a map answers this long before its deadline, with what it waits for
#: (the deadline's own 503 cannot say).
ANSWER_MARGIN_S = 0.5


@dataclass(frozen=True)
class MapState:
    """The map of one region version: the posterior of its field."""

    spec: RegionSpec
    region_id: str
    version: int
    posterior: Posterior | Mixture

    @property
    def nbytes(self) -> int:
        return self.posterior.nbytes

    @property
    def map(self) -> RegionMap:
        """What queries read: the posterior with the spec that checks their points."""
        return RegionMap(self.spec, self.posterior)


class PosteriorCache:
    """Least-recently-used map states, bounded by their memory (``max_mb``)."""

    def __init__(self, max_mb: float = 512.0):
        self.max_bytes = int(max_mb * 2**20)
        self._items: OrderedDict[tuple, MapState] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def get(self, key: tuple) -> MapState | None:
        with self._lock:
            state = self._items.get(key)
            if state is None:
                self.misses += 1
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return state

    def peek(self, key: tuple) -> MapState | None:
        """:meth:`get` that counts no hit or miss (a look, not a use)."""
        with self._lock:
            return self._items.get(key)

    def put(self, key: tuple, state: MapState) -> None:
        """Hold ``state`` (replacing the one held of its version: a settled map replaces
        the one before)."""
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= old.nbytes
            self._items[key] = state
            self._bytes += state.nbytes
            while self._bytes > self.max_bytes and len(self._items) > 1:
                _, old = self._items.popitem(last=False)
                self._bytes -= old.nbytes

    @property
    def nbytes(self) -> int:
        return self._bytes

    def __contains__(self, key: tuple) -> bool:
        """Held, without counting a hit or a miss (a look before the query that counts)."""
        return key in self._items

    def __len__(self) -> int:
        return len(self._items)


@dataclass
class RefreshStats:
    """What the refreshes did (``/metrics``)."""

    count: int = 0  # maps computed here
    seconds: float = 0.0  # their total time
    loaded: int = 0  # maps loaded from the store (computed by another process, or before a restart)
    skipped: int = 0  # versions never computed: a newer one was written first
    factorisations: int = 0  # of their hyperparameter searches (and fixed values)
    last_s: float = 0.0
    failed: int = 0  # refreshes that raised (the previous map kept answering)
    settled: int = 0  # of the maps computed, those computed again to settle their "auto" hyperparameters
    settling_seconds: float = 0.0  # their total time
    abandoned: int = 0  # settling passes given up for a newer version (its refresh runs at once)
    last_gap: float = 0.0  # nats the last map's hyperparameters lack from its evidence maximum


@dataclass
class RegionRefresh:
    """One region's refreshes in this process (fields under the refresher's lock)."""

    building: threading.Lock = field(default_factory=threading.Lock)  # one computation at a time
    newest: MapState | None = None  # the newest map here (of the region instance it names)
    finished: deque = field(default_factory=lambda: deque(maxlen=8))  # (time, version) of its maps
    running: bool = False  # a refresh thread runs
    again: bool = False  # written again since it began: it runs once more
    settling: tuple[int, int] | None = None  # (job, version) of the settling pass under way
    computing: tuple[int, float] | None = None  # (version, since) computed now, here or by the lease's holder
    took: float | None = None  # seconds the last map took, here or where it was computed
    begun: int = 0  # refreshes begun (they run in order)
    ended: int = 0  # refreshes ended
    failure: tuple[int, Exception] | None = None  # (refresh, its error)
    computed: str | None = None  # region_id of the last refresh's map


class Refresher:
    """The maps of a store's regions, computed by background refreshes once for every
    process (module doc)."""

    #: Regions whose decoded tile evidence is kept for the next refresh (most recent).
    EVIDENCE_REGIONS = 8

    def __init__(
        self, store: MapStore, cache_mb: float = 512.0, isolate: bool = False, lease_s: float = LEASE_S
    ):
        """``isolate``: compute posteriors in a child process (the service does). A
        posterior takes seconds of CPU on a city's lattice, part of it under the GIL (the
        steps between the compiled kernels), and in this process that would stall every
        request its other threads serve."""
        self.store, self.lease_s = store, lease_s
        self.holder = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"  # in leases
        self.cache = PosteriorCache(cache_mb)
        self.stats = RefreshStats()
        self._isolate, self._pool = isolate, None  # the child starts with the first posterior
        #: the settling pass a newer version abandons (its job number; shared with the child)
        self._shared = _shared()
        self._abandon = self._shared.abandon
        self._jobs = itertools.count(1)
        self._spawner = _Spawner(self._shared) if isolate else None
        self._lock = threading.Lock()
        self._done = threading.Condition(self._lock)  # a refresh ended (waiters look again)
        self._regions: dict[str, RegionRefresh] = {}
        self._threads: dict[str, threading.Thread] = {}
        self._evidence: OrderedDict[str, dict] = OrderedDict()  # region_id -> key -> (version, evidence)
        self._closed = False

    def _region(self, name: str) -> RegionRefresh:
        with self._lock:
            return self._regions.setdefault(name, RegionRefresh())

    # -- lifetime --------------------------------------------------------------------------------
    def open(self) -> None:
        """Refresh again after :meth:`close` (an app started again after its shutdown)."""
        with self._lock:
            self._closed = False
            if self._isolate and not (self._spawner and self._spawner.alive):
                self._spawner = _Spawner(self._shared)  # posterior processes run at this thread's priority

    def close(self) -> None:
        """Stop the background refreshes (after the ones under way): the store closes next."""
        with self._done:
            self._closed, threads = True, list(self._threads.values())
            self._done.notify_all()
        for thread in threads:
            thread.join(timeout=120)
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        if self._spawner is not None:
            self._spawner.stop()

    def join(self, timeout: float) -> bool:
        """Wait until no refresh runs (tests, before they change the store under it); False
        if one still runs after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        with self._done:
            while self._threads:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._done.wait(left)
        return True

    # -- what readers see ------------------------------------------------------------------------
    def newest(self, info: RegionInfo) -> MapState | None:
        """The newest map here of the region instance ``info`` names."""
        with self._lock:
            entry = self._regions.get(info.spec.name)
            newest = entry.newest if entry else None
        return newest if newest is not None and newest.region_id == info.region_id else None

    def finished(self, info: RegionInfo) -> list[tuple[float, int]]:
        """(time, version) of the region's last maps published here (computed, or loaded
        with the time they were computed)."""
        with self._lock:
            entry = self._regions.get(info.spec.name)
            if entry is None or entry.newest is None or entry.newest.region_id != info.region_id:
                return []
            return list(entry.finished)

    def publish(self, state: MapState, when: float | None = None) -> None:
        """Serve ``state`` here (``when``: the time it was computed, now if None)."""
        self.cache.put((state.region_id, state.version), state)
        entry = self._region(state.spec.name)
        with self._lock:
            newest = entry.newest
            if newest is not None and newest.region_id != state.region_id:
                newest = None
                entry.finished.clear()
            if newest is None or (newest.version, newest.posterior.settled) < (state.version, True):
                entry.newest = state
            entry.finished.append((time.time() if when is None else when, state.version))

    def store_map(self, state: MapState, seconds: float) -> None:
        """Store ``state``'s map for the other processes; a store that cannot be written now
        costs only that (they compute it themselves)."""
        try:
            self.store.save_map(
                state.region_id,
                state.version,
                state.posterior.settled,
                seconds,
                encode_posterior(state.posterior),
            )
        except StoreUnavailable as exc:
            log.warning("region %s: map of version %d not stored: %s", state.spec.name, state.version, exc)

    # -- waiting ---------------------------------------------------------------------------------
    def wait(self, info: RegionInfo, at_least: int, settled: bool = False) -> MapState:
        """A map of the region instance ``info`` at version ``at_least`` or newer (at most
        the version read: no later one is known to exist; ``settled``: its hyperparameters
        settled), waiting for the refreshes to compute it (one is scheduled), until the
        deadline. A refresh that fails raises its error here."""
        region, at_least = info.spec.name, min(at_least, info.version)
        entry = self._region(region)
        with self._done:
            mine = entry.begun + 1  # the first refresh to read the store from now
            self._schedule_locked(region, info.version)
            while True:
                newest = entry.newest
                if serves(newest, info, at_least, settled):
                    return newest
                if self._closed:
                    raise lanes.Overloaded("the service is shutting down: no map is computed now", 5)
                if entry.ended >= mine:  # it ended short of the version
                    failed, error = entry.failure or (0, None)
                    if failed >= mine:
                        raise error
                    if entry.computed != info.region_id:
                        raise RegionChanged(f"region {region!r} was deleted or re-created meanwhile")
                    mine = entry.begun + 1
                    self._schedule_locked(region, info.version)
                left = lanes.remaining() - ANSWER_MARGIN_S  # answer before the deadline does
                timeout = None if left == math.inf else max(left, 0.0)
                if not self._done.wait(timeout=timeout) and left <= 0:
                    raise self.not_ready(region, at_least)

    def not_ready(self, region: str, version: int) -> lanes.Overloaded:
        """503 for a read whose map is not ready: which version is computed, since when, how
        long the last took, and when to come back (its Retry-After)."""
        entry = self._regions.get(region) or RegionRefresh()
        computing, took = entry.computing, entry.took
        if computing is None:
            what = f"the map of region {region!r} at version {version} waits for its refresh"
            elapsed = 0.0
        else:
            at, since = computing
            elapsed = time.time() - since
            started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(since))
            what = f"the map of region {region!r} at version {at} is computed since {started}"
            what += f" ({elapsed:.0f} s)"
        last = "" if took is None else f"; the last took {took:.1f} s"
        retry = max(1, math.ceil((took or 5.0) - elapsed))
        return lanes.Overloaded(f"{what}{last}: retry in {retry} s", retry)

    # -- the schedule ----------------------------------------------------------------------------
    def schedule(self, region: str, version: int = 0) -> None:
        """Refresh the region's map in the background: one refresh per region at a time; a
        write during one makes it run once more, for the newest version then. ``version``:
        the newest known to the caller; a settling pass of an older one is abandoned."""
        with self._lock:
            self._schedule_locked(region, version)

    def _schedule_locked(self, region: str, version: int = 0) -> None:
        """:meth:`schedule`, holding ``self._lock``."""
        if self._closed:
            return
        entry = self._regions.setdefault(region, RegionRefresh())
        if entry.settling is not None and version > entry.settling[1]:
            self._abandon.value = entry.settling[0]
        if entry.running:
            entry.again = True
            return
        entry.running, entry.again = True, False
        thread = threading.Thread(
            target=self._loop, args=(region, entry), name=f"refresh-{region}", daemon=True
        )
        self._threads[region] = thread
        thread.start()

    def _loop(self, region: str, entry: RegionRefresh) -> None:
        while True:
            error = computed = None
            with self._lock:
                entry.begun += 1
            try:
                state = self.compute(region, self.store.region(region).version)
                with self._lock:
                    quiet = not entry.again
                if quiet and not state.posterior.settled:  # no newer version waits: settle this one
                    state = self.compute(region, state.version, settle=True, yields=True)
                computed = state.region_id
            except RegionNotFound as exc:
                error = exc
            except Exception as exc:  # the previous version keeps answering
                error = exc
                log.error(
                    "refreshing region %s failed (%s: %s); its previous version keeps answering",
                    region,
                    type(exc).__name__,
                    exc,
                    exc_info=not isinstance(exc, StoreUnavailable | lanes.Overloaded),
                )
            with self._done:
                entry.ended += 1
                entry.computed = computed
                if error is not None:
                    entry.failure = (entry.ended, error)
                    self.stats.failed += not isinstance(error, RegionNotFound)
                self._done.notify_all()
                if entry.again and not self._closed:
                    entry.again = False
                    continue
                entry.running = False
                self._threads.pop(region, None)
                return

    # -- computing -------------------------------------------------------------------------------
    def compute(self, region: str, at_least: int, settle: bool = False, yields: bool = False) -> MapState:
        """A map of the region at version ``at_least`` or newer: one published or stored
        meanwhile (a caller waiting here shares the refresh under way), else the current
        version's, computed now under the region's lease. One computation per region at a
        time. "auto" hyperparameters start at the newest map's; without ``settle`` they may
        stop within a nat of the evidence maximum, with it they are at the maximum (a map
        within a nat of it is computed again). ``yields`` (the background's settling pass):
        a newer version written meanwhile abandons it, and the newest map is returned as it
        was: the newer version's refresh starts at once."""
        entry = self._region(region)
        with entry.building:
            try:
                found, info, newest = self._ready_or_leased(region, entry, at_least, settle)
            finally:
                with self._lock:
                    entry.computing = None  # whoever computed it is done (or this one starts)
            if found is not None:
                return found
            try:
                with self._renewing(info):
                    return self._computed(region, entry, info, newest, settle, yields)
            finally:
                with self._lock:
                    entry.computing = None
                with contextlib.suppress(StoreUnavailable):
                    self.store.release_lease(info.region_id, self.holder)

    def _ready_or_leased(self, region: str, entry: RegionRefresh, at_least: int, settle: bool):
        """``(map, info, newest)``: a map that serves (cached, published or stored), or None
        once this process holds the region's lease to compute the version of ``info``;
        meanwhile another process's lease is waited out (its map loaded once stored)."""
        while True:
            info = self.store.region(region)
            state = self.cache.get((info.region_id, info.version))
            if state is not None and (state.posterior.settled or not settle):
                return state, info, None
            newest = self.newest(info)
            if serves(newest, info, at_least, settle):
                return newest, info, newest
            stored = self._load(info, settle)
            if stored is not None:
                return stored, info, newest
            lease = self.store.take_lease(info.region_id, self.holder, info.version, self.lease_s)
            if lease.holder == self.holder:
                return None, info, newest
            with self._done:  # another process computes it: its map is loaded once stored
                entry.computing = (lease.version, lease.since)
                if self._closed:
                    raise lanes.Overloaded("the service is shutting down: no map is computed now", 5)
                self._done.wait(LEASE_POLL_S)

    def _computed(
        self, region: str, entry: RegionRefresh, info: RegionInfo, newest, settle: bool, yields: bool
    ) -> MapState:
        """:meth:`compute`'s work, the lease held: the map of the store's current version,
        published and stored."""
        started = time.perf_counter()
        job = next(self._jobs) if yields else 0
        with self._lock:
            entry.computing = (info.version, time.time())
            if yields:
                entry.settling = (job, info.version)
        try:
            snap, evidence = self._snapshot_evidence(region, info.region_id)
            spec = snap.region.spec
            start = self.start(snap.region, newest)
            post = self.posterior(spec, region_total(spec, evidence), start, settle=settle, job=job)
        except hyperparameters.Abandoned:
            with self._lock:
                self.stats.abandoned += 1
            log.info("region %s: settling version %d abandoned for a newer version", region, info.version)
            return newest
        finally:
            with self._lock:
                if yields:
                    entry.settling = None
        state = MapState(spec, snap.region.region_id, snap.region.version, post)
        seconds = time.perf_counter() - started
        self.publish(state)
        self.store_map(state, seconds)
        with self._lock:
            entry.took = seconds
            self.stats.count += 1
            self.stats.seconds += seconds
            self.stats.last_s = seconds
            self.stats.factorisations += post.factorisations
            self.stats.last_gap = post.evidence_gap
            if newest is not None:
                self.stats.skipped += max(state.version - newest.version - 1, 0)
                again = newest.version == state.version
                self.stats.settled += again
                self.stats.settling_seconds += seconds * again
        log.info(
            "region %s version %d: map ready in %.2f s (%d factorisations, %s)",
            region,
            state.version,
            seconds,
            post.factorisations,
            "settled" if post.settled else f"{post.evidence_gap:.2g} nats from the evidence maximum",
        )
        if spec.auto and post.fitted:
            self._record(region, state)
        return state

    def _load(self, info: RegionInfo, settle: bool) -> MapState | None:
        """Publish the store's map of the region instance if it is newer than this process's
        (another process computed it, or this one before a restart); return it if it is of
        ``info``'s version (and ``settle``: settled)."""
        stored = self.store.stored_map(info.region_id)
        if stored is None:
            return None
        entry = self._region(info.spec.name)
        with self._lock:
            entry.took = stored.seconds
        newest = self.newest(info)
        if newest is None or (newest.version, newest.posterior.settled) < (stored.version, stored.settled):
            try:
                loaded = self.store.load_map(info.region_id)
                if loaded is None:
                    return None
                stored, blob = loaded
                post = decode_posterior(blob)
            except (CorruptTile, ValueError) as exc:  # damaged, or another code's: computed again
                log.warning(
                    "region %s: stored map of version %d unreadable (%s)", info.spec.name, stored.version, exc
                )
                self.store.drop_map(info.region_id, stored.version)
                return None
            self.publish(MapState(info.spec, info.region_id, stored.version, post), when=stored.computed_at)
            with self._lock:
                self.stats.loaded += 1
            log.info("region %s version %d: map loaded from the store", info.spec.name, stored.version)
        state = self.newest(info)
        return state if serves(state, info, info.version, settle) else None

    @contextlib.contextmanager
    def _renewing(self, info: RegionInfo):
        """Renew the region's lease every third of it while the block runs."""
        stop = threading.Event()

        def renew():
            while not stop.wait(self.lease_s / 3):
                try:
                    self.store.take_lease(info.region_id, self.holder, info.version, self.lease_s)
                except (StoreUnavailable, RegionChanged) as exc:
                    log.warning("region %s: lease not renewed: %s", info.spec.name, exc)

        thread = threading.Thread(target=renew, name=f"lease-{info.spec.name}", daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()

    def posterior(
        self, spec: RegionSpec, evidence, start=None, stored=True, settle=True, job=0
    ) -> Posterior | Mixture:
        """``compute_posterior(spec, evidence, start, stored=..., settle=...)``, in the child
        process if isolated; a settling pass ``job`` (> 0) raises
        :class:`bdf.hyperparameters.Abandoned` once a newer version abandons it."""
        if not self._isolate:
            return _compute_posterior(spec, evidence, start, stored, settle, job, self._abandon)
        for attempt in range(2):
            with self._lock:
                if self._pool is None:
                    self._pool = self._spawner.start()
                pool = self._pool
            try:
                future = pool.submit(_compute_posterior, spec, evidence, start, stored, settle, job)
                return future.result(timeout=lanes.wait_timeout())
            except concurrent.futures.TimeoutError:
                raise lanes.DeadlineExceeded(
                    "the request's deadline passed while its map was computed; nothing was stored"
                ) from None
            except BrokenProcessPool:  # the child died (killed, out of memory): start another
                if attempt:
                    raise
                log.warning("the posterior process died; starting another")
                with self._lock:
                    if self._pool is pool:
                        self._pool = None

    def choose(
        self, spec: RegionSpec, rows: tuple, progress: Callable[[float], None] | None = None
    ) -> Choice:
        """:func:`bdf.region.resolution.choose_directions` (a fit of a region of
        ``directions: "auto"``), ``progress`` followed; if isolated, in a process of its own:
        its minutes of cross-validation hold up no other region's refresh."""
        if not self._isolate:
            return choose_directions(spec, rows, progress)
        shared = _shared()
        pool = self._spawner.start(shared)
        try:
            return _followed(pool.submit(_choose_directions, spec, rows), progress, shared.progress)
        except concurrent.futures.TimeoutError:
            raise lanes.DeadlineExceeded(
                "the request's deadline passed while its heading sectors were chosen; nothing was stored"
            ) from None
        finally:
            pool.shutdown(wait=False)

    def _snapshot_evidence(self, region: str, region_id: str):
        """The region's snapshot and every tile's evidence, decoding only the tiles whose
        version changed since the last refresh here (of the instance ``region_id``)."""
        with self._lock:
            kept = self._evidence.pop(region_id, {})
        snap = self.store.snapshot(
            region, need=lambda rid, key, version: kept.get(key, (None,))[0] != version
        )
        if snap.region.region_id != region_id:  # re-created meanwhile
            kept = {}
            snap = self.store.snapshot(region)
        tiles = {
            key: (info.version, snap.evidence[key] if key in snap.evidence else kept[key][1])
            for key, info in snap.tiles.items()
        }
        with self._lock:
            self._evidence[snap.region.region_id] = tiles
            while len(self._evidence) > self.EVIDENCE_REGIONS:
                self._evidence.popitem(last=False)
        return snap, {key: evidence for key, (_, evidence) in tiles.items()}

    def start(self, info: RegionInfo, newest: MapState | None = None):
        """Where the "auto" search of ``info``'s region starts: the optimum of its newest map
        here, or the one the store records (another process's, or before a restart)."""
        if not info.spec.auto:
            return None
        if newest is not None and newest.spec == info.spec and newest.posterior.fitted:
            return newest.posterior.next_start
        hyper = info.hyper or {}
        rows = info.spec.posteriors
        try:
            start = np.asarray(hyper["alpha"], float) / np.asarray(hyper["beta"], float)
        except (KeyError, TypeError, ValueError):
            return None
        if start.shape != ((3,) if rows == 1 else (rows, 3)) or not np.all(np.isfinite(start) & (start > 0)):
            return None
        return start

    def _record(self, region: str, state: MapState) -> None:
        """Record the hyperparameters the map of ``state`` found (the region view shows
        them; a new process starts its search there). A store that cannot be written now
        costs only the record."""
        try:
            self.store.record_hyperparameters(region, state.region_id, fitted(state.posterior), state.version)
        except (StoreUnavailable, RegionChanged, RegionNotFound) as exc:
            log.warning(
                "region %s: hyperparameters of version %d not recorded: %s", region, state.version, exc
            )


def serves(state: MapState | None, info: RegionInfo, at_least: int, settled: bool) -> bool:
    """``state`` answers a query of the region instance ``info`` that needs version
    ``at_least`` (and ``settled`` hyperparameters)."""
    return (
        state is not None
        and state.region_id == info.region_id
        and state.version >= at_least
        and state.spec == info.spec
        and (state.posterior.settled or not settled)
    )


def fitted(post: Posterior | Mixture) -> dict | None:
    """The record of hyperparameters fitted by evidence maximisation (store module doc);
    None when the spec fixes both (nothing was fitted)."""
    if not post.fitted:
        return None
    return {
        "alpha": post.alpha.tolist(),
        "beta": post.beta.tolist(),
        "log_evidence": post.log_evidence.tolist(),
        "fitted_at": time.time(),
        "settled": bool(post.settled),
        "evidence_gap": float(post.evidence_gap),
        "at_bound": bool(post.at_bound),
        "plausibility": post.plausibility,
    }


def _compute_posterior(spec: RegionSpec, evidence, start, stored, settle, job=0, abandon=None):
    """:func:`bdf.region.map.compute_posterior` (a module function: what the posterior process
    runs), given up (:class:`bdf.hyperparameters.Abandoned`) once ``abandon`` (the posterior
    process's: :data:`_ABANDON`) holds the number of this settling pass, ``job``."""
    abandon = abandon if abandon is not None else _ABANDON
    with hyperparameters.abandon_when(lambda: job > 0 and abandon.value == job):
        return compute_posterior(spec, evidence, start, stored=stored, settle=settle)


def _choose_directions(spec: RegionSpec, rows: tuple) -> Choice:
    """:func:`bdf.region.resolution.choose_directions` in a child process, its progress in
    :data:`_PROGRESS`."""
    return choose_directions(spec, rows, lambda fraction: setattr(_PROGRESS, "value", fraction))


def _followed(future: concurrent.futures.Future, progress, shared):
    """``future``'s result within the request's deadline (``TimeoutError`` past it), reporting
    ``shared.value`` to ``progress`` every :data:`PROGRESS_POLL_S` meanwhile."""
    left = lanes.wait_timeout()
    end = None if left is None else time.monotonic() + left
    while True:
        wait = PROGRESS_POLL_S if end is None else min(PROGRESS_POLL_S, max(end - time.monotonic(), 0.0))
        try:
            return future.result(timeout=wait)
        except concurrent.futures.TimeoutError:
            if end is not None and time.monotonic() >= end:
                raise
            if progress is not None:
                progress(shared.value)


class _Shared(NamedTuple):
    """What a child process shares with its parent."""

    abandon: object  # the number of the settling pass its parent abandons (:data:`_ABANDON`)
    progress: object  # how far its work is, a fraction (:data:`_PROGRESS`)


def _shared() -> _Shared:
    """Fresh values to share with a child process (spawned)."""
    return _Shared(*(multiprocessing.get_context("spawn").Value(t, 0, lock=False) for t in "qd"))


#: In a child process: the number of the settling pass its parent abandons, and how far
#: its work is.
_ABANDON = None
_PROGRESS = None
#: How often a wait for a child process reports its progress (s).
PROGRESS_POLL_S = 0.5


#: How often the posterior process checks that the process that started it lives (s).
PARENT_CHECK_S = 1.0


def _posterior_process(shared: _Shared) -> ProcessPoolExecutor:
    """One child process for posteriors (spawned: this process runs threads), sharing
    ``shared`` (:data:`_ABANDON`, :data:`_PROGRESS`). It leaves when this process dies:
    killed, a pool cannot tell its child, which would wait for work forever, holding its
    memory (a quarter of a GB on the demo's map)."""
    return ProcessPoolExecutor(
        1,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_posterior_child,
        initargs=(os.getpid(), shared),
    )


class _Spawner:
    """Starts posterior processes from a thread of this process's own priority: a process
    inherits the priority of the thread that starts it, and the lanes' threads run at a
    lower one (:data:`service.lanes.NICE`) so that maps are computed first."""

    def __init__(self, shared: _Shared):
        self._shared = shared
        self._asked: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="posterior-spawner", daemon=True)
        self._thread.start()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def start(self, shared: _Shared | None = None) -> ProcessPoolExecutor:
        """A child process sharing ``shared`` (the posterior process's if None)."""
        if not self.alive:
            raise lanes.Overloaded("the service is shutting down: no map is computed now", 5)
        started: concurrent.futures.Future = concurrent.futures.Future()
        self._asked.put((started, shared or self._shared))
        return started.result()

    def stop(self) -> None:
        self._asked.put(None)
        self._thread.join(timeout=10)

    def _run(self) -> None:
        while True:
            asked = self._asked.get()
            if asked is None:
                return
            started, shared = asked
            try:
                pool = _posterior_process(shared)
                pool.submit(os.getpid)  # the child is spawned now, by this thread
                started.set_result(pool)
            except Exception as exc:
                started.set_exception(exc)


def _posterior_child(parent: int, shared: _Shared) -> None:
    """In a child process: keep ``shared`` (:data:`_ABANDON`, :data:`_PROGRESS`); exit
    once ``parent`` is no longer its parent."""
    global _ABANDON, _PROGRESS
    _ABANDON, _PROGRESS = shared

    def watch():
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_S)
        os._exit(0)

    threading.Thread(target=watch, name="leave-with-parent", daemon=True).start()
