"""The map layer the routes call: uploads into tiles, queries of the region's one field.

Writes go to the store (:mod:`service.store`, the truth) and schedule their region's
refresh; reads answer from the maps the refreshes compute once for every process
(:mod:`service.refresh`). Each answer says which version it is and how far behind the
region it is (:class:`MapPrediction`): until a version's map is ready, queries answer from
the newest map there is, and a query that asks for at least a version (``min_version``:
read your own writes) waits for it, until its deadline (:mod:`service.lanes`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from time import perf_counter  # upload has a parameter named time

import numpy as np

from bdf.posterior import Modes
from bdf.region.evidence import accepted_rows_increments, checked_rows, region_total
from bdf.region.route import assess as assess_route
from bdf.region.spec import RegionSpec
from service import lanes
from service.refresh import MapState, Refresher, fitted, serves
from service.store import MapStore, RegionChanged, RegionInfo, ResolutionChanged, payload_digest

log = logging.getLogger(__name__)
#: Times an upload is computed again when fits keep choosing other heading sectors meanwhile.
RESOLUTION_RETRIES = 3


class Unprocessable(ValueError):
    """A well-formed request this region cannot apply (no row accepted, nothing to fit):
    the client's to change (422); nothing was stored."""


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
    refreshes_behind: int = 0  # maps finished since then (at most 1: each refresh is of the newest)
    evidence_gap: float = 0.0  # nats its "auto" hyperparameters lack from the maximum (0: settled)


class RegionMaps:
    """Region maps over a :class:`MapStore`: exactly-once uploads, queries of the region's
    field, maps refreshed in the background (module doc)."""

    #: Points computed between deadline checks.
    CHUNK = 4096
    #: Voxels of a grid's slab (of x) computed between deadline checks: each slab pays its
    #: separable contractions over y and z whole (slabs of 4,096 voxels, one x value of a
    #: 100 x 100 x 30 grid, and a second density gather made that grid 302-381 ms over HTTP
    #: against 166-168 now: ``bench/bench_service.py``'s grid rows)
    GRID_SLAB = 32768

    def __init__(self, store: MapStore, cache_mb: float = 512.0, isolate: bool = False, **refresh):
        """``isolate``: compute posteriors in a child process (:class:`service.refresh.Refresher`,
        which ``refresh`` keywords configure)."""
        self.store = store
        store.before_commit = lanes.check  # a write past its deadline rolls back
        self.refresher = Refresher(store, cache_mb, isolate, **refresh)
        self.cache, self.stats = self.refresher.cache, self.refresher.stats
        self.open, self.close = self.refresher.open, self.refresher.close
        self._committed = CommittedTimes(store)
        store.on_close(self.refresher.close)

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
        :class:`Unprocessable` and stores nothing. A fit of a region of ``directions:
        "auto"`` chooses its heading sectors (:mod:`bdf.region.resolution`) and stores the
        choice with its tiles; an upload computed meanwhile for the sectors before is
        computed again (:data:`RESOLUTION_RETRIES` times at most, then 409).
        """
        rows = checked_rows(X, V, input_noise_std, sample_weight, track, time)
        digest = payload_digest(upload_kind(replace), *rows)
        first = self.store.upload_result(region, upload_id, digest)
        if first is not None:
            return first
        attempts = RESOLUTION_RETRIES
        while True:
            try:
                return self._apply_rows(region, upload_id, digest, rows, replace, progress)
            except ResolutionChanged:  # a fit chose other sectors while these were computed
                attempts -= 1
                if attempts == 0:
                    raise

    def _apply_rows(self, region, upload_id, digest, rows, replace, progress) -> dict:
        """:meth:`upload` of checked rows not in the ledger: the region's spec read once."""
        info = self.store.region(region)
        spec, chosen = info.spec, None
        started = perf_counter()
        if replace and spec.directions == "auto":  # the fit chooses the heading resolution
            spec, increments, summary, post = self.refresher.choose(spec, rows, _checkpoint(progress))
            chosen = spec
        else:
            increments, summary = accepted_rows_increments(spec, *rows, progress=_checkpoint(progress))
        _log_warnings(spec, summary)
        require_accepted(summary, "fit" if replace else "upload")
        if replace and chosen is None:
            evidence = region_total(spec, {k: i.evidence for k, i in increments.items()})
            post = self.refresher.posterior(spec, evidence, self.refresher.start(info), stored=False)
        seconds = perf_counter() - started
        result = self.store.apply(
            region,
            info.region_id,
            upload_id,
            digest,
            increments,
            observations=summary["accepted"],
            replace=replace,
            summary=summary,
            hyper=fitted(post) if replace else None,
            spec=chosen,
        )
        if replace and not result["replayed"]:  # the map of exactly this version
            state = MapState(spec, info.region_id, result["region_version"], post)
            self.refresher.publish(state)
            self.refresher.store_map(state, seconds)
        else:
            self.refresher.schedule(region, result["region_version"])
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
        increments, summary = accepted_rows_increments(info.spec, *rows, progress=_checkpoint(None))
        _log_warnings(info.spec, summary)
        result = self.store.retract(
            region,
            info.region_id,
            upload_id,
            payload_digest("observations", *rows),
            increments,
            observations=summary["accepted"],
        )
        self.refresher.schedule(region, result["region_version"])
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
        self.refresher.wait(info, info.version, settled=True)
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
        slab = max(1, self.GRID_SLAB // max(rest[0].size * rest[1].size, 1))
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
        return self.refresher.compute(region, self.store.region(region).version, settle=True)

    def wait_for(self, info: RegionInfo, min_version: int = 0) -> MapState:
        """Wait (until the deadline) for the map a query of ``info`` with ``min_version``
        needs: after it, :meth:`ready` is true."""
        return self.refresher.wait(info, max(min_version, 1 if info.version else 0))

    def ready(self, info: RegionInfo, min_version: int = 0) -> bool:
        """A query of the region as read (``info``) would be answered without waiting for
        a map to be computed."""
        if (info.region_id, info.version) in self.cache:
            return True
        return serves(self.refresher.newest(info), info, min_version, False)

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
        since = self._committed.of(info, state.version + 1)
        # maps without the version after the answer's, finished since it was written
        finished = self.refresher.finished(info)
        refreshes = sum(t > since and version <= state.version for t, version in finished)
        return behind, max(time.time() - since, 0.0), refreshes, gap

    def _state(self, region: str, info: RegionInfo, min_version: int) -> MapState:
        """The map at ``info``'s version if ready; else the newest ready one (a refresh is
        scheduled) if it is at least ``min_version``; else it waits for one that is."""
        state = self.cache.get((info.region_id, info.version))
        if state is not None:
            return state
        newest = self.refresher.newest(info)
        if serves(newest, info, min_version, False):
            self.refresher.schedule(region, info.version)
            return newest
        return self.wait_for(info, min_version)


class CommittedTimes:
    """When versions of regions were written, read from the store once each (a version's
    time never changes), the :data:`KEEP` most recent kept: the answers' lag."""

    KEEP = 256

    def __init__(self, store: MapStore):
        self.store = store
        self._times: OrderedDict[tuple, float] = OrderedDict()  # (region_id, version) -> time
        self._lock = threading.Lock()

    def of(self, info: RegionInfo, version: int) -> float:
        """When ``version`` of the region ``info`` was written (its ``updated_at`` for a
        version written before the store kept versions' times)."""
        key = (info.region_id, version)
        since = self._times.get(key)
        if since is not None:
            return since
        since = self.store.committed_at(*key)
        if since is None:
            return info.updated_at
        with self._lock:
            self._times[key] = since
            while len(self._times) > self.KEEP:
                self._times.popitem(last=False)
        return since


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


def upload_kind(replace: bool) -> str:
    return "fit" if replace else "observations"


def upload_digest(kind: str, X, V, input_noise_std=None, sample_weight=None, track=None, time=None) -> str:
    """The ledger's digest of an upload (``kind``: :func:`upload_kind`) of these rows."""
    return payload_digest(kind, *checked_rows(X, V, input_noise_std, sample_weight, track, time))


def _log_warnings(spec: RegionSpec, summary: dict) -> None:
    """The log line for rows without a track id (an answer carries the warning too)."""
    for warning in summary.get("warnings", []):
        log.warning("%s: %d %s", spec.name, summary["untracked"], warning)


def require_accepted(summary: dict, what: str) -> None:
    """:class:`Unprocessable` unless some row was accepted: a fit of nothing would wipe the
    map, an upload of nothing would bump its version for no change."""
    if summary["accepted"] == 0:
        reasons = ", ".join(f"{n} {r}" for r, n in summary["rejected"].items() if n) or "no rows"
        raise Unprocessable(f"no row of the {what} was accepted ({reasons}); nothing was stored")
