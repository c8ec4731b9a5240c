"""The map layer the routes call: uploads into tiles, queries of the region's one field.

The store holds the truth (tile statistics, versions, ledger); a region's map is derived
data: the posterior of the sum of its tiles' evidence at the spec's hyperparameters
("auto": the evidence maximum of that version's data, whatever uploads brought it), per
``(region_id, version)``, kept in a memory-bounded LRU.

Refreshes: a write answers at once and schedules its region's refresh. One refresh per
region runs at a time, always of the newest version (versions written meanwhile are
skipped, not queued: the next refresh starts from the newest), warm from the last (the
tiles' decoded evidence whose version has not changed, the previous optimum as the
search's start, the symbolic analysis of an unchanged support in the posterior process).
Until it is ready, queries answer from the newest map this process has, and each answer
says which version it is and how far behind (:class:`MapPrediction`); a query that asks for
at least a version (``min_version``: read your own writes) waits for the refresh, until
its deadline (:mod:`service.lanes`). Only refreshes compute a version's map, so a reader
that gives up wastes nothing: the map it waited for is ready for the next.
"""

from __future__ import annotations

import concurrent.futures
import itertools
import logging
import math
import multiprocessing
import os
import queue
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np

from bdf import hyperparameters
from bdf.posterior import Mixture, Modes, Posterior
from bdf.region.evidence import accepted_rows_increments, checked_rows, region_total
from bdf.region.map import RegionMap, compute_posterior
from bdf.region.route import assess as assess_route
from bdf.region.spec import RegionSpec
from service import lanes
from service.store import (
    MapStore,
    RegionChanged,
    RegionInfo,
    RegionNotFound,
    StoreUnavailable,
    payload_digest,
)

log = logging.getLogger(__name__)


class Unprocessable(ValueError):
    """A well-formed request this region cannot apply (no row accepted, nothing to fit):
    the client's to change (422); nothing was stored."""


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


@dataclass(frozen=True)
class MapAssessment:
    """A route's metrics on the map of one region version, and how far that is behind."""

    result: dict
    version: int
    region_id: str
    behind: int
    behind_s: float
    refreshes_behind: int
    evidence_gap: float


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
class MapPrediction:
    mean: np.ndarray  # (n, 3) m/s
    std: np.ndarray  # (n, 3) predictive std, m/s
    known: np.ndarray  # (n,) data lies within the kernel's reach
    version: int  # region version the answer was computed from
    region_id: str  # with the version, names the map state (ETag)
    modes: Modes | None = None  # per traffic class, when asked
    behind: int = 0  # versions written that the answer's map does not hold yet
    behind_s: float = 0.0  # since when (s): the age of the first of them
    refreshes_behind: int = 0  # maps finished here since then (at most 1: each refresh is of the newest)
    evidence_gap: float = 0.0  # nats its "auto" hyperparameters lack from the maximum (0: settled)


#: A read waiting for a map answers this long before its deadline, with what it waits for
#: (the deadline's own 503 cannot say).
ANSWER_MARGIN_S = 0.5


@dataclass
class RefreshStats:
    """What the refreshes did (``/metrics``)."""

    count: int = 0  # maps computed
    seconds: float = 0.0  # their total time
    skipped: int = 0  # versions never computed: a newer one was written first
    factorisations: int = 0  # of their hyperparameter searches (and fixed values)
    last_s: float = 0.0
    failed: int = 0  # refreshes that raised (the previous map kept answering)
    settled: int = 0  # of the maps computed, those computed again to settle their "auto" hyperparameters
    settling_seconds: float = 0.0  # their total time
    abandoned: int = 0  # settling passes given up for a newer version (its refresh runs at once)
    last_gap: float = 0.0  # nats the last map's hyperparameters lack from its evidence maximum


class RegionMaps:
    """Region maps over a :class:`MapStore`: exactly-once uploads, queries of the region's
    field, maps refreshed in the background (module doc)."""

    #: Regions whose decoded tile evidence is kept for the next refresh (most recent).
    EVIDENCE_REGIONS = 8
    #: Commit times of versions kept for the answers' lag (most recent).
    COMMITTED_TIMES = 256
    #: Points (or grid slabs of about as many voxels) computed between deadline checks.
    CHUNK = 4096

    def __init__(self, store: MapStore, cache_mb: float = 512.0, isolate: bool = False):
        """``isolate``: compute posteriors in a child process (the service does). A
        posterior takes seconds of CPU on a city's lattice, part of it under the GIL (the
        steps between the compiled kernels), and in this process that would stall every
        request its other threads serve."""
        self.store = store
        store.before_commit = lanes.check  # a write past its deadline rolls back
        self._isolate, self._pool = isolate, None  # the child starts with the first posterior
        #: the settling pass a newer version abandons (its job number; shared with the child)
        self._abandon = multiprocessing.get_context("spawn").Value("q", 0, lock=False)
        self._jobs = itertools.count(1)
        self._spawner = _Spawner(self._abandon) if isolate else None
        self.cache = PosteriorCache(cache_mb)
        self.stats = RefreshStats()
        self._newest: dict[str, MapState] = {}  # region_id -> newest state computed here
        self._lock = threading.Lock()
        self._building: dict[str, threading.Lock] = {}  # region name -> one computation at a time
        self._refreshing: dict[str, bool] = {}  # region name -> written again since it started
        self._settling: dict[str, tuple[int, int]] = {}  # region name -> (job, version) settling now
        self._finished: dict[str, deque] = {}  # region_id -> (time, version) of its last maps published here
        self._done = threading.Condition(self._lock)  # a refresh ended (waiters look again)
        self._begun: dict[str, int] = {}  # region name -> refreshes begun (they run in order)
        self._ended: dict[str, int] = {}  # region name -> refreshes ended
        self._failure: dict[str, tuple[int, Exception]] = {}  # region name -> (refresh, its error)
        self._computed: dict[str, str] = {}  # region name -> region_id of its last refresh
        self._computing: dict[str, tuple[int, float]] = {}  # region name -> (version, since) of its refresh
        self._took: dict[str, float] = {}  # region name -> seconds its last map took here
        self._threads: dict[str, threading.Thread] = {}
        self._evidence: OrderedDict[str, dict] = OrderedDict()  # region_id -> key -> (version, evidence)
        self._committed: OrderedDict[tuple, float] = OrderedDict()  # (region_id, version) -> time
        self._closed = False
        store.on_close(self.close)

    def open(self) -> None:
        """Refresh again after :meth:`close` (an app started again after its shutdown)."""
        with self._lock:
            self._closed = False
            if self._isolate and not (self._spawner and self._spawner.alive):
                self._spawner = _Spawner(self._abandon)  # posterior processes run at this thread's priority

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

    def _posterior(
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

    def upload(
        self,
        region: str,
        upload_id: str,
        X,
        V,
        *,
        input_noise_std=None,
        sample_weight=None,
        track=None,
        time=None,
        replace: bool = False,
        progress: Callable[[float], None] | None = None,
    ) -> dict:
        """Apply observations (ENU metres, m/s) to a region once per ``upload_id``.

        Rows with a non-finite value, outside the region or outside its envelope are
        rejected and counted, the rest accepted. ``track`` (integer codes, -1: none) and
        ``time`` (seconds): the rows of a track are weighed by :func:`bdf.ingest.track_weights`
        (times ``sample_weight``); rows without one count as independent observations, and
        the result says how many (``untracked``, with a warning). ``replace``: the map becomes this data
        alone (a fit): its posterior is computed before anything is stored, so a fit that
        cannot be solved raises ``ValueError`` and changes nothing. An upload answers
        without waiting for its map (a refresh is scheduled). Returns the ledger result:
        accepted, rejected (by reason), tiles_updated, region_version, replayed.
        ``progress(fraction)`` follows the per-tile work. With no row accepted it raises
        :class:`Unprocessable` and stores nothing.
        """
        rows = checked_rows(X, V, input_noise_std, sample_weight, track, time)
        digest = payload_digest(upload_kind(replace), *rows)
        first = self.store.upload_result(region, upload_id, digest)
        if first is not None:
            return first
        info = self.store.region(region)
        spec = info.spec
        increments, summary = _accepted(spec, rows, _checkpoint(progress))
        require_accepted(summary, "fit" if replace else "upload")
        post = None
        if replace:
            evidence = region_total(spec, {k: i.evidence for k, i in increments.items()})
            post = self._posterior(spec, evidence, self._start(info), stored=False)
        result = self.store.apply(
            region,
            info.region_id,
            upload_id,
            digest,
            increments,
            observations=summary["accepted"],
            replace=replace,
            summary=summary,
            hyper=None if post is None else fitted(post),
        )
        if post is not None and not result["replayed"]:  # the map of exactly this version
            state = MapState(spec, info.region_id, result["region_version"], post)
            self._publish(state)
        else:
            self._schedule(region, result["region_version"])
        return result

    def retract(
        self,
        region: str,
        upload_id: str,
        X,
        V,
        *,
        input_noise_std=None,
        sample_weight=None,
        track=None,
        time=None,
    ) -> dict:
        """Retract the applied upload ``upload_id``, given its rows again (as sent to
        :meth:`upload`): the region's map becomes the map without it (the store's
        ``retract``); once per upload id, a retry replays the result."""
        rows = checked_rows(X, V, input_noise_std, sample_weight, track, time)
        info = self.store.region(region)
        increments, summary = _accepted(info.spec, rows, _checkpoint(None))
        result = self.store.retract(
            region,
            info.region_id,
            upload_id,
            payload_digest("observations", *rows),
            increments,
            observations=summary["accepted"],
        )
        self._schedule(region, result["region_version"])
        return result

    def fit_hyperparameters(self, region: str) -> RegionInfo:
        """The region's map at its current version: its "auto" hyperparameters are that
        version's evidence maximum (every refresh finds them; this waits for it, until the
        deadline). Returns the region with them. :class:`Unprocessable` if the spec fixes
        both or the region has no data."""
        info = self.store.region(region)
        if not info.spec.auto:
            raise Unprocessable(f"region {region!r} fixes alpha and beta in its spec: nothing to fit")
        if not info.tiles:
            raise Unprocessable(f"region {region!r} has no data to fit its hyperparameters on")
        self._wait(region, info, info.version, settled=True)
        now = self.store.region(region)
        if now.region_id != info.region_id:
            raise RegionChanged(f"region {region!r} was deleted or re-created while its map was computed")
        return now

    def predict(
        self,
        region: str,
        X,
        info: RegionInfo | None = None,
        min_version: int = 0,
        *,
        heading_deg=None,
        modes: bool = False,
    ) -> MapPrediction:
        """Mean, std and ``known`` at ENU points ``X`` (n, 3) inside the region.

        ``info``: the region as the caller read it (its version names the map wanted).
        ``min_version``: answer from at least this version (waiting for its map).
        ``heading_deg``: the mode of traffic flying it instead of the mixture; ``modes``:
        every class's share, mean and std too.
        """
        info = info or self.store.region(region)
        state = self._state(region, info, min_version)
        X = np.asarray(X, float)
        if heading_deg is not None and np.ndim(heading_deg):
            heading_deg = np.asarray(heading_deg, float)
        parts = []
        for lo in range(0, max(len(X), 1), self.CHUNK):  # a deadline check between chunks
            lanes.check()
            part = slice(lo, lo + self.CHUNK)
            heading = heading_deg[part] if heading_deg is not None and np.ndim(heading_deg) else heading_deg
            per_class = state.map.predict_modes(X[part]) if modes else None
            parts.append((*state.map.predict(X[part], heading, per_class), per_class))
        mean, std, known, per_class = _joined(parts, axis=0)
        return MapPrediction(
            mean, std, known, state.version, state.region_id, per_class, *self._lag(info, state)
        )

    def assess(self, region: str, query, info: RegionInfo, min_version: int = 0) -> MapAssessment:
        """:func:`bdf.region.route.assess` of a decoded route (:class:`service.formats.RouteQuery`)
        on the region's map."""
        state = self._state(region, info, min_version)
        lanes.check()
        result = assess_route(
            state.map,
            query.P,
            max_std_mps=query.max_std_mps,
            craft=query.vehicle,
            times_s=query.times_s,
            heading_deg=query.heading_deg,
            checkpoint=lanes.check,
        )
        return MapAssessment(result, state.version, state.region_id, *self._lag(info, state))

    def predict_grid(
        self, region: str, axes, info: RegionInfo | None = None, min_version: int = 0, *, modes: bool = False
    ) -> MapPrediction:
        """:meth:`predict` on the grid ``axes[0] x axes[1] x axes[2]``: arrays shaped
        (nx, ny, nz, 3) and (nx, ny, nz), the modes' (nx, ny, nz, C, ...)."""
        info = info or self.store.region(region)
        state = self._state(region, info, min_version)
        x, rest = np.asarray(axes[0], float), [np.asarray(a, float) for a in axes[1:]]
        slab = max(1, self.CHUNK // max(rest[0].size * rest[1].size, 1))
        parts = []
        for lo in range(0, max(x.size, 1), slab):  # a deadline check between slabs of x
            lanes.check()
            sub = [x[lo : lo + slab], *rest]
            per_class = state.map.predict_grid_modes(sub) if modes else None
            parts.append((*state.map.predict_grid(sub, per_class), per_class))
        mean, std, known, per_class = _joined(parts, axis=0)
        return MapPrediction(
            mean, std, known, state.version, state.region_id, per_class, *self._lag(info, state)
        )

    def refresh(self, region: str) -> MapState:
        """The settled map state of the region's current version, computed now if need be
        (in the caller's thread: builds and tests; the service's readers wait for refreshes)."""
        return self._compute(region, self.store.region(region).version, settle=True)

    def wait_for(self, info: RegionInfo, min_version: int = 0) -> MapState:
        """Wait (until the deadline) for the map a query of ``info`` with ``min_version``
        needs: after it, :meth:`ready` is true."""
        return self._wait(info.spec.name, info, max(min_version, 1 if info.version else 0))

    def ready(self, info: RegionInfo, min_version: int = 0) -> bool:
        """A query of the region as read (``info``) would be answered without waiting for
        a map to be computed."""
        if (info.region_id, info.version) in self.cache:
            return True
        with self._lock:
            newest = self._newest.get(info.region_id)
        return _serves(newest, info.spec, min_version, False)

    def settled(self, info: RegionInfo) -> bool:
        """The map of ``info``'s version is computed here and its hyperparameters settled."""
        state = self.cache.peek((info.region_id, info.version))
        return state is not None and state.posterior.settled

    def _lag(self, info: RegionInfo, state: MapState) -> tuple[int, float, int, float]:
        """How far ``state`` is behind the region as read (``info``): versions, the seconds
        since the first of them was written, the maps of the region published here since
        then without it (each refresh computes the newest version when it begins, so at
        most the one under way then), and the nats its hyperparameters lack from its data's
        evidence maximum (0 once settled)."""
        gap = state.posterior.evidence_gap
        behind = info.version - state.version if info.region_id == state.region_id else 0
        if behind <= 0:
            return 0, 0.0, 0, gap
        key = (info.region_id, state.version + 1)
        since = self._committed.get(key)  # a version's time never changes: read it once
        if since is None:
            since = self.store.committed_at(*key)
            if since is None:  # written before the store kept versions' times
                since = info.updated_at
            else:
                with self._lock:
                    self._committed[key] = since
                    while len(self._committed) > self.COMMITTED_TIMES:
                        self._committed.popitem(last=False)
        with self._lock:  # maps without the version after the answer's, finished since it was written
            finished = list(self._finished.get(state.region_id, ()))
        refreshes = sum(t > since and version <= state.version for t, version in finished)
        return behind, max(time.time() - since, 0.0), refreshes, gap

    def _state(self, region: str, info: RegionInfo, min_version: int) -> MapState:
        """The map at ``info``'s version if ready; else the newest ready one (a refresh is
        scheduled) if it is at least ``min_version``; else it waits for one that is."""
        state = self.cache.get((info.region_id, info.version))
        if state is not None:
            return state
        with self._lock:
            newest = self._newest.get(info.region_id)
        if _serves(newest, info.spec, min_version, False):
            self._schedule(region, info.version)
            return newest
        return self.wait_for(info, min_version)

    def _wait(self, region: str, info: RegionInfo, at_least: int, settled: bool = False) -> MapState:
        """A map of the region instance ``info`` at version ``at_least`` or newer (at most
        the version read: no later one is known to exist; ``settled``: its hyperparameters
        settled), waiting for the refreshes to compute it (one is scheduled), until the
        deadline. A refresh that fails raises its error here."""
        at_least = min(at_least, info.version)
        with self._done:
            mine = self._begun.get(region, 0) + 1  # the first refresh to read the store from now
            self._schedule_locked(region, info.version)
            while True:
                newest = self._newest.get(info.region_id)
                if _serves(newest, info.spec, at_least, settled):
                    return newest
                if self._closed:
                    raise lanes.Overloaded("the service is shutting down: no map is computed now", 5)
                if self._ended.get(region, 0) >= mine:  # it ended short of the version
                    failed, error = self._failure.get(region, (0, None))
                    if failed >= mine:
                        raise error
                    if self._computed.get(region) != info.region_id:
                        raise RegionChanged(f"region {region!r} was deleted or re-created meanwhile")
                    mine = self._begun.get(region, 0) + 1
                    self._schedule_locked(region, info.version)
                left = lanes.remaining() - ANSWER_MARGIN_S  # answer before the deadline does
                timeout = None if left == math.inf else max(left, 0.0)
                if not self._done.wait(timeout=timeout) and left <= 0:
                    raise self._not_ready(region, at_least)

    def _not_ready(self, region: str, version: int) -> lanes.Overloaded:
        """503 for a read whose map is not ready: which version is computed, since when, how
        long the last took, and when to come back (its Retry-After)."""
        computing, took = self._computing.get(region), self._took.get(region)
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

    def _compute(self, region: str, at_least: int, settle: bool = False, yields: bool = False) -> MapState:
        """A map of the region at version ``at_least`` or newer: one computed meanwhile (a
        caller waiting here shares the refresh under way), else the current version's,
        computed now. One computation per region at a time. "auto" hyperparameters start at
        the newest map's; without ``settle`` they may stop within a nat of the evidence
        maximum (a refresh in the background: the map is fresh sooner), with it they are at
        the maximum (a map within a nat of it is computed again). ``yields`` (the
        background's settling pass): a newer version written meanwhile abandons it, and the
        newest map is returned as it was: the newer version's refresh starts at once."""
        with self._lock:
            lock = self._building.setdefault(region, threading.Lock())
        with lock:
            info = self.store.region(region)
            state = self.cache.get((info.region_id, info.version))
            if state is not None and (state.posterior.settled or not settle):
                return state
            with self._lock:
                newest = self._newest.get(info.region_id)
            if _serves(newest, info.spec, at_least, settle):
                return newest
            started = time.perf_counter()
            job = next(self._jobs) if yields else 0
            with self._lock:
                self._computing[region] = (info.version, time.time())
                if yields:
                    self._settling[region] = (job, info.version)
            try:
                snap, evidence = self._snapshot_evidence(region, info.region_id)
                spec = snap.region.spec
                start = self._start(snap.region, newest)
                post = self._posterior(spec, region_total(spec, evidence), start, settle=settle, job=job)
            except hyperparameters.Abandoned:
                with self._lock:
                    self.stats.abandoned += 1
                log.info("region %s: settling version %d abandoned for a newer version", region, info.version)
                return newest
            finally:
                with self._lock:
                    self._computing.pop(region, None)
                    if yields:
                        self._settling.pop(region, None)
            state = MapState(spec, snap.region.region_id, snap.region.version, post)
            self._publish(state)
            seconds = time.perf_counter() - started
            with self._lock:
                self._took[region] = seconds
                self.stats.count += 1
                self.stats.seconds += seconds
                self.stats.last_s = seconds
                self.stats.factorisations += post.factorisations
                self.stats.last_gap = post.evidence_gap
                if newest is not None and newest.region_id == state.region_id:
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

    def _start(self, info: RegionInfo, newest: MapState | None = None):
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

    def _publish(self, state: MapState) -> None:
        self.cache.put((state.region_id, state.version), state)
        with self._lock:
            newest = self._newest.get(state.region_id)
            if newest is None or (newest.version, newest.posterior.settled) < (state.version, True):
                self._newest[state.region_id] = state
            self._finished.setdefault(state.region_id, deque(maxlen=8)).append((time.time(), state.version))

    def _schedule(self, region: str, version: int = 0) -> None:
        """Refresh the region's map in the background: one refresh per region at a time; a
        write during one makes it run once more, for the newest version then. ``version``:
        the newest known to the caller; a settling pass of an older one is abandoned."""
        with self._lock:
            self._schedule_locked(region, version)

    def _schedule_locked(self, region: str, version: int = 0) -> None:
        """:meth:`_schedule`, holding ``self._lock``."""
        if self._closed:
            return
        settling = self._settling.get(region)
        if settling is not None and version > settling[1]:
            self._abandon.value = settling[0]
        if region in self._refreshing:
            self._refreshing[region] = True
            return
        self._refreshing[region] = False
        thread = threading.Thread(
            target=self._refresh_loop, args=(region,), name=f"refresh-{region}", daemon=True
        )
        self._threads[region] = thread
        thread.start()

    def _refresh_loop(self, region: str) -> None:
        while True:
            error = computed = None
            with self._lock:
                self._begun[region] = self._begun.get(region, 0) + 1
            try:
                state = self._compute(region, self.store.region(region).version)
                with self._lock:
                    quiet = not self._refreshing.get(region)
                if quiet and not state.posterior.settled:  # no newer version waits: settle this one
                    state = self._compute(region, state.version, settle=True, yields=True)
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
                    exc_info=not isinstance(exc, StoreUnavailable),
                )
            with self._done:
                ended = self._ended[region] = self._ended.get(region, 0) + 1
                self._computed[region] = computed
                if error is not None:
                    self._failure[region] = (ended, error)
                    self.stats.failed += not isinstance(error, RegionNotFound)
                self._done.notify_all()
                if self._refreshing.get(region) and not self._closed:
                    self._refreshing[region] = False
                    continue
                self._refreshing.pop(region, None)
                self._threads.pop(region, None)
                return


def _serves(state: MapState | None, spec: RegionSpec, at_least: int, settled: bool) -> bool:
    """``state`` answers a query of a region of ``spec`` that needs version ``at_least``
    (and ``settled`` hyperparameters)."""
    return (
        state is not None
        and state.version >= at_least
        and state.spec == spec
        and (state.posterior.settled or not settled)
    )


def _checkpoint(progress: Callable[[float], None] | None) -> Callable[[float], None]:
    """``progress``, checking the deadline at each step (per tile) of the work."""

    def step(fraction: float) -> None:
        lanes.check()
        if progress is not None:
            progress(fraction)

    return step


def _joined(parts: list[tuple], axis: int) -> tuple:
    """Chunks' (mean, std, known, modes) joined along ``axis`` (the points, or x)."""
    if len(parts) == 1:
        return parts[0]
    mean, std, known = (np.concatenate([p[i] for p in parts], axis=axis) for i in range(3))
    modes = parts[0][3]
    if modes is not None:
        modes = Modes(*(np.concatenate([p[3][i] for p in parts], axis=axis) for i in range(len(modes))))
    return mean, std, known, modes


def _compute_posterior(spec: RegionSpec, evidence, start, stored, settle, job=0, abandon=None):
    """:func:`bdf.region.map.compute_posterior` (a module function: what the posterior process
    runs), given up (:class:`bdf.hyperparameters.Abandoned`) once ``abandon`` (the posterior
    process's: :data:`_ABANDON`) holds the number of this settling pass, ``job``."""
    abandon = abandon if abandon is not None else _ABANDON
    with hyperparameters.abandon_when(lambda: job > 0 and abandon.value == job):
        return compute_posterior(spec, evidence, start, stored=stored, settle=settle)


#: In the posterior process: the number of the settling pass its parent abandons.
_ABANDON = None


#: How often the posterior process checks that the process that started it lives (s).
PARENT_CHECK_S = 1.0


def _posterior_process(abandon) -> ProcessPoolExecutor:
    """One child process for posteriors (spawned: this process runs threads), sharing
    ``abandon`` (:data:`_ABANDON`). It leaves when this process dies: killed, a pool cannot
    tell its child, which would wait for work forever, holding its memory (a quarter of a GB
    on the demo's map)."""
    return ProcessPoolExecutor(
        1,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_posterior_child,
        initargs=(os.getpid(), abandon),
    )


class _Spawner:
    """Starts posterior processes from a thread of this process's own priority: a process
    inherits the priority of the thread that starts it, and the lanes' threads run at a
    lower one (:data:`service.lanes.NICE`) so that maps are computed first."""

    def __init__(self, abandon):
        self._abandon = abandon
        self._asked: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="posterior-spawner", daemon=True)
        self._thread.start()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def start(self) -> ProcessPoolExecutor:
        if not self.alive:
            raise lanes.Overloaded("the service is shutting down: no map is computed now", 5)
        started: concurrent.futures.Future = concurrent.futures.Future()
        self._asked.put(started)
        return started.result()

    def stop(self) -> None:
        self._asked.put(None)
        self._thread.join(timeout=10)

    def _run(self) -> None:
        while True:
            started = self._asked.get()
            if started is None:
                return
            try:
                pool = _posterior_process(self._abandon)
                pool.submit(os.getpid)  # the child is spawned now, by this thread
                started.set_result(pool)
            except Exception as exc:
                started.set_exception(exc)


def _posterior_child(parent: int, abandon) -> None:
    """In the posterior process: keep ``abandon`` (:data:`_ABANDON`); exit once ``parent``
    is no longer its parent."""
    global _ABANDON
    _ABANDON = abandon

    def watch():
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_S)
        os._exit(0)

    threading.Thread(target=watch, name="leave-with-parent", daemon=True).start()


def fitted(post: Posterior) -> dict | None:
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


def upload_kind(replace: bool) -> str:
    return "fit" if replace else "observations"


def upload_digest(kind: str, X, V, input_noise_std=None, sample_weight=None, track=None, time=None) -> str:
    """The ledger's digest of an upload (``kind``: :func:`upload_kind`) of these rows."""
    return payload_digest(kind, *checked_rows(X, V, input_noise_std, sample_weight, track, time))


def _accepted(spec: RegionSpec, rows: tuple, progress) -> tuple[dict, dict]:
    """:func:`bdf.region.evidence.accepted_increments` of checked rows, and the log line for
    rows without a track id (an answer carries the warning too)."""
    tile_increments, summary = accepted_rows_increments(spec, *rows, progress=progress)
    for warning in summary.get("warnings", []):
        log.warning("%s: %d %s", spec.name, summary["untracked"], warning)
    return tile_increments, summary


def require_accepted(summary: dict, what: str) -> None:
    """:class:`Unprocessable` unless some row was accepted: a fit of nothing would wipe the
    map, an upload of nothing would bump its version for no change."""
    if summary["accepted"] == 0:
        reasons = ", ".join(f"{n} {r}" for r, n in summary["rejected"].items() if n) or "no rows"
        raise Unprocessable(f"no row of the {what} was accepted ({reasons}); nothing was stored")
