"""Per-request bookkeeping as one ASGI middleware: body size limit, deadline, Prometheus
metrics, request ids, security headers, the answer to an error of ours, and one structured
log line per request (route, status, duration, region, request id; never other headers,
so never tokens).
"""

from __future__ import annotations

import json
import logging
import re
import time

import anyio
from prometheus_client import CollectorRegistry, Counter, Histogram, disable_created_metrics
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from service import lanes
from service.problems import DEADLINE_RETRY_S, Problem, new_request_id, problem
from service.wire import REQUEST_ID_HEADER

#: a client's request id is kept if it is a plain token (it goes into logs and headers)
REQUEST_ID = re.compile(r"[A-Za-z0-9._-]{1,64}")
#: on every response: no MIME sniffing, no referrer leaks, no framing of the viewer
#: (its own policy, with the scripts it needs, is set on the viewer route)
SECURITY_HEADERS = [
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
    (b"x-frame-options", b"DENY"),
]
disable_created_metrics()  # the *_created series only add noise to every scrape
access_log = logging.getLogger("bdf.access")
log = logging.getLogger("bdf.service")
LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30)


class Metrics:
    """The service's Prometheus registry (one per app, so tests can build several apps)."""

    def __init__(self, maps, work_lanes: lanes.Lanes):
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "bdf_http_requests", "HTTP requests", ["route", "method", "status"], registry=self.registry
        )
        self.latency = Histogram(
            "bdf_http_request_duration_seconds",
            "HTTP request latency",
            ["route", "method"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.uploads = Counter(
            "bdf_uploads_applied", "uploads, fits and retractions applied", ["kind"], registry=self.registry
        )
        self.observations = Counter(
            "bdf_observations", "observations received, by outcome", ["outcome"], registry=self.registry
        )
        self.versions_behind = Histogram(
            "bdf_answer_versions_behind",
            "region versions written that an answer's map did not hold yet",
            buckets=(0, 1, 2, 3, 5, 10, 20, 50, 100),
            registry=self.registry,
        )
        self.seconds_behind = Histogram(
            "bdf_answer_seconds_behind",
            "age of the first region version an answer's map did not hold (0: current)",
            buckets=(0, *LATENCY_BUCKETS, 60, 300),
            registry=self.registry,
        )
        self.refreshes_behind = Histogram(
            "bdf_answer_refreshes_behind",
            "maps of the region finished since the first version an answer's map did not hold "
            "was written (at most 1: each refresh computes the newest version)",
            buckets=(0, 1, 2, 3, 5),
            registry=self.registry,
        )
        self.deadlines = Counter(
            "bdf_request_deadlines", "requests answered 503 at their deadline", registry=self.registry
        )
        self.registry.register(_StateCollector(maps, work_lanes))

    def answered(self, versions_behind: int, seconds_behind: float, refreshes_behind: int) -> None:
        self.versions_behind.observe(versions_behind)
        self.seconds_behind.observe(seconds_behind)
        self.refreshes_behind.observe(refreshes_behind)

    def upload_applied(self, result: dict) -> None:
        if result.get("replayed"):
            return
        self.uploads.labels(result["kind"]).inc()
        if result["kind"] == "retraction":  # its rows were counted when they arrived
            self.observations.labels("retracted").inc(result["accepted"])
            return
        self.observations.labels("accepted").inc(result["accepted"])
        for reason, count in result["rejected"].items():
            self.observations.labels(f"rejected_{reason}").inc(count)


class _StateCollector:
    """The lanes, the posterior cache and the refreshes, read at each scrape."""

    def __init__(self, maps, work_lanes: lanes.Lanes):
        self.maps, self.lanes = maps, work_lanes

    def collect(self):
        families = (
            (GaugeMetricFamily, "bdf_lane_busy", "threads at work per lane", lambda st: st.busy),
            (
                GaugeMetricFamily,
                "bdf_lane_waiting",
                "requests waiting for a thread per lane",
                lambda st: max(st.admitted - st.busy, 0),
            ),
            (
                CounterMetricFamily,
                "bdf_lane_shed",
                "requests refused at once: lane full (503)",
                lambda st: st.shed,
            ),
            (
                CounterMetricFamily,
                "bdf_lane_expired",
                "requests whose deadline passed while waiting for a thread (503)",
                lambda st: st.expired,
            ),
        )
        for family, name, doc, value in families:
            metric = family(name, doc, labels=["lane"])
            for lane in (self.lanes.light, self.lanes.heavy, self.lanes.waiting):
                metric.add_metric([lane.name], value(lane.stats))
            yield metric
        yield from self._maps()

    def _maps(self):
        cache, refreshes = self.maps.cache, self.maps.stats
        rows = [
            (CounterMetricFamily, "bdf_posterior_cache_hits", "region maps served from memory", cache.hits),
            (CounterMetricFamily, "bdf_posterior_cache_misses", "region maps not in memory", cache.misses),
            (GaugeMetricFamily, "bdf_posterior_cache_bytes", "memory held by cached maps", cache.nbytes),
            (CounterMetricFamily, "bdf_map_refreshes", "region maps computed here", refreshes.count),
            (
                CounterMetricFamily,
                "bdf_map_loads",
                "region maps loaded from the store: computed by another process, or before a restart",
                refreshes.loaded,
            ),
            (CounterMetricFamily, "bdf_map_refresh_seconds", "time computing region maps", refreshes.seconds),
            (GaugeMetricFamily, "bdf_map_refresh_last_seconds", "the last map's time", refreshes.last_s),
            (
                CounterMetricFamily,
                "bdf_map_versions_skipped",
                "region versions never computed: a newer one was written first",
                refreshes.skipped,
            ),
            (
                CounterMetricFamily,
                "bdf_map_factorisations",
                "factorisations of the maps' hyperparameter searches",
                refreshes.factorisations,
            ),
            (CounterMetricFamily, "bdf_map_refresh_failures", "refreshes that failed", refreshes.failed),
            (
                CounterMetricFamily,
                "bdf_map_settles",
                "maps computed again to settle their 'auto' hyperparameters at the evidence maximum",
                refreshes.settled,
            ),
            (
                CounterMetricFamily,
                "bdf_map_settling_seconds",
                "time computing maps again to settle them (part of bdf_map_refresh_seconds)",
                refreshes.settling_seconds,
            ),
            (
                CounterMetricFamily,
                "bdf_map_settles_abandoned",
                "settling passes given up for a newer version, whose refresh ran at once",
                refreshes.abandoned,
            ),
            (
                GaugeMetricFamily,
                "bdf_map_evidence_gap_nats",
                "nats the last map's 'auto' hyperparameters lack from its evidence maximum",
                refreshes.last_gap,
            ),
        ]
        for family, name, doc, value in rows:
            metric = family(name, doc)
            metric.add_metric([], value)
            yield metric


def _outcome(scope) -> str:
    """What a client whose request ran out of time knows of its outcome. A read stores
    nothing. A write stops before its commit once the deadline passed (the store's
    ``before_commit``), but one that committed just before it is answered late: its outcome
    is not known here, and a retry under the same Idempotency-Key is applied at most once."""
    route = scope.get("route")
    if getattr(route, "openapi_extra", None) and route.openapi_extra.get("x-scope") == "read":
        return f"retry in {DEADLINE_RETRY_S} s"
    return (
        "the write may have been stored or not; retry it with the same Idempotency-Key (an upload, "
        "fit or retraction is applied at most once), or read the region's version to see"
    )


class RequestMiddleware:
    """Gives every request an id (the client's ``X-Request-ID`` when it is a plain token, else
    a new one), returned in that header and in every problem body; adds the headers every
    response carries (:data:`SECURITY_HEADERS`); bounds the body; sets the deadline
    (``timeout_s``: 503 past it, :mod:`service.lanes`); answers an error of ours (500, one
    log line with its traceback, ``Connection: close``); counts and logs."""

    def __init__(self, app, max_body_bytes: int, metrics: Metrics, timeout_s: float = 30.0):
        self.app, self.max_body_bytes, self.metrics, self.timeout_s = app, max_body_bytes, metrics, timeout_s

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        start = time.perf_counter()
        status, started = 500, False
        headers = dict(scope["headers"])
        given = headers.get(b"x-request-id", b"").decode("latin-1")
        request_id = given if REQUEST_ID.fullmatch(given) else new_request_id()
        scope.setdefault("state", {})["request_id"] = request_id
        extra = [(REQUEST_ID_HEADER.lower().encode(), request_id.encode()), *SECURITY_HEADERS]

        async def send_with_headers(message):
            nonlocal status, started
            if message["type"] == "http.response.start":
                started = True
                status = message["status"]
                present = {name.lower() for name, _ in message.get("headers", ())}
                message["headers"] = [*message.get("headers", ()), *(h for h in extra if h[0] not in present)]
            await send(message)

        try:
            length = headers.get(b"content-length")
            if length is not None and length.isdigit() and int(length) > self.max_body_bytes:
                return await problem(413, self._too_large(), scope)(scope, receive, send_with_headers)
            received = 0

            async def limited_receive():
                nonlocal received
                message = await receive()
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    raise Problem(413, self._too_large())
                return message

            # uvicorn's receive is its request cycle's, which knows when the client has left
            cycle = getattr(receive, "__self__", None)
            with (
                lanes.client(lambda: getattr(cycle, "disconnected", False)),
                lanes.deadline(self.timeout_s),
                anyio.move_on_after(self.timeout_s) as timer,
            ):
                await self.app(scope, limited_receive, send_with_headers)
            if timer.cancelled_caught:
                self.metrics.deadlines.inc()
                if not started:
                    detail = f"no answer within the deadline of {self.timeout_s:g} s: {_outcome(scope)}"
                    headers = {"Retry-After": str(DEADLINE_RETRY_S), "Connection": "close"}
                    await problem(503, detail, scope, headers)(scope, receive, send_with_headers)
        except Exception:  # ours: logged once here (the server never sees it), answered 500
            log.exception("request %s (%s %s) failed", request_id, scope["method"], scope["path"])
            if not started:
                detail = "internal error (logged on the server with this request id)"
                await problem(500, detail, scope, {"Connection": "close"})(scope, receive, send_with_headers)
        finally:
            self._record(scope, status, time.perf_counter() - start, request_id)

    def _too_large(self) -> str:
        return f"the request body exceeds the limit of {self.max_body_bytes / 2**20:g} MiB; split it"

    def _record(self, scope, status: int, seconds: float, request_id: str) -> None:
        route = getattr(scope.get("route"), "path", "unmatched")
        self.metrics.requests.labels(route, scope["method"], str(status)).inc()
        self.metrics.latency.labels(route, scope["method"]).observe(seconds)
        if access_log.isEnabledFor(logging.INFO):
            line = {
                "method": scope["method"],
                "route": route,
                "status": status,
                "ms": round(seconds * 1e3, 2),
                "region": scope.get("path_params", {}).get("name"),
                "request_id": request_id,
            }
            access_log.info(json.dumps(line))
