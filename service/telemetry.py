"""Per-request bookkeeping as one ASGI middleware: body size limit, Prometheus metrics,
and one structured log line per request (route, status, duration, region; never headers).
"""

from __future__ import annotations

import json
import logging
import time

from prometheus_client import CollectorRegistry, Counter, Histogram, disable_created_metrics
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from service.problems import Problem, problem

disable_created_metrics()  # the *_created series only add noise to every scrape
access_log = logging.getLogger("bdf.access")
LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30)


class Metrics:
    """The service's Prometheus registry (one per app, so tests can build several apps)."""

    def __init__(self, cache):
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
            "bdf_uploads_applied", "uploads and fits applied", ["kind"], registry=self.registry
        )
        self.observations = Counter(
            "bdf_observations", "observations received, by outcome", ["outcome"], registry=self.registry
        )
        self.registry.register(_CacheCollector(cache))

    def upload_applied(self, result: dict) -> None:
        if result.get("replayed"):
            return
        self.uploads.labels(result["kind"]).inc()
        self.observations.labels("accepted").inc(result["accepted"])
        for reason, count in result["rejected"].items():
            self.observations.labels(f"rejected_{reason}").inc(count)


class _CacheCollector:
    def __init__(self, cache):
        self.cache = cache

    def collect(self):
        hits = CounterMetricFamily("bdf_posterior_cache_hits", "region posteriors served from memory")
        hits.add_metric([], self.cache.hits)
        misses = CounterMetricFamily("bdf_posterior_cache_misses", "region posteriors not in memory")
        misses.add_metric([], self.cache.misses)
        size = GaugeMetricFamily("bdf_posterior_cache_bytes", "memory held by cached posteriors")
        size.add_metric([], self.cache.nbytes)
        yield from (hits, misses, size)


class RequestMiddleware:
    def __init__(self, app, max_body_bytes: int, metrics: Metrics):
        self.app, self.max_body_bytes, self.metrics = app, max_body_bytes, metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        start = time.perf_counter()
        status = 500
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.max_body_bytes:
            response = problem(413, self._too_large(), scope["path"])
            return await response(scope, receive, send)
        received = 0

        async def limited_receive():
            nonlocal received
            message = await receive()
            received += len(message.get("body", b""))
            if received > self.max_body_bytes:
                raise Problem(413, self._too_large())
            return message

        async def send_status(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, limited_receive, send_status)
        finally:
            self._record(scope, status, time.perf_counter() - start)

    def _too_large(self) -> str:
        return f"the request body exceeds the limit of {self.max_body_bytes / 2**20:g} MiB; split it"

    def _record(self, scope, status: int, seconds: float) -> None:
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
            }
            access_log.info(json.dumps(line))
