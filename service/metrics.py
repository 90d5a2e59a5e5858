"""Prometheus metrics and the recent-latency window that /health reports."""

import os
import time
from collections import deque

import numpy as np
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
    multiprocess,
)
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.features import FAILURES

# Methods labelled by name; any other (clients may send made-up ones) is counted as "other".
HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "DELETE", "OPTIONS", "PATCH", "TRACE", "CONNECT"})
LATENCY_BUCKETS = (0.01, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0, 5.0, 10.0, 30.0)
# The folder of every worker's values, which prometheus_client reads as it is imported.
WORKERS_FOLDER_VARIABLE = "PROMETHEUS_MULTIPROC_DIR"


class Metrics:
    """The service's metrics, in a registry of their own so that several apps (tests) can coexist.

    Under several workers (WORKERS_FOLDER_VARIABLE set by the supervisor before they start),
    every worker writes its values to files there and /metrics, whichever worker answers it, adds
    up those of all of them: counts and histograms summed, the queue depth of live workers summed,
    readiness the least of theirs.
    """

    def __init__(self, max_batch_size: int):
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "ifnet_http_requests",
            "HTTP requests by route and status code.",
            ["method", "route", "status"],
            registry=self.registry,
        )
        self.request_latency = Histogram(
            "ifnet_http_request_duration_seconds",
            "Time to answer an HTTP request.",
            ["route"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.queue_wait = Histogram(
            "ifnet_queue_wait_seconds",
            "Time a pair waited in its model's queue before its model call.",
            ["model"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.inference = Histogram(
            "ifnet_inference_seconds",
            "Duration of one ONNX Runtime call (a whole batch).",
            ["model"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.batch_size = Histogram(
            "ifnet_batch_size",
            "Pairs per model call.",
            ["model"],
            buckets=tuple(range(1, max_batch_size + 1)),
            registry=self.registry,
        )
        self.queue_depth = Gauge(
            "ifnet_queue_depth",
            "Pairs waiting for a model.",
            ["model"],
            registry=self.registry,
            multiprocess_mode="livesum",
        )
        self.rejections = Counter(
            "ifnet_batcher_rejections",
            "Pairs a model's batcher did not run, by reason.",
            ["model", "reason"],
            registry=self.registry,
        )
        self.answers = Counter(
            "ifnet_answers",
            "Registered pairs by the model and stage that gave the answer and whether it was verified.",
            ["model", "stage", "verified"],
            registry=self.registry,
        )
        self.feature_matching_failures = Counter(
            "ifnet_feature_matching_failures",
            "Feature matching's child process crashed or gave no answer in time (crash, timeout); the pairs in it "
            "were answered without its guess.",
            ["reason"],
            registry=self.registry,
        )
        for reason in FAILURES:  # at zero from the start, so that a rate over them is defined
            self.feature_matching_failures.labels(reason)
        self.feature_matching_replaced = Counter(
            "ifnet_feature_matching_replaced",
            "Feature matching's child process replaced by a new one after its resident memory passed "
            "IFNET_FEATURE_MATCHING_MAX_MB.",
            registry=self.registry,
        )
        self.ready = Gauge(
            "ifnet_ready",
            "1 once every model is loaded and warmed up (in every worker).",
            registry=self.registry,
            multiprocess_mode="livemin",
        )
        # An info metric as a gauge of 1: prometheus_client's Info is not shared between workers.
        self.model = Gauge(
            "ifnet_model_info",
            "A served model.",
            ["model", "version", "network_points"],
            registry=self.registry,
            multiprocess_mode="max",
        )

    def add_model(self, name: str, version: str, network_points: int) -> None:
        """Its info, and its series at zero from the start, so that a model not yet asked still shows."""
        self.model.labels(name, version, str(network_points)).set(1)
        for metric in (self.queue_wait, self.inference, self.batch_size, self.queue_depth):
            metric.labels(name)

    def render(self) -> tuple[bytes, str]:
        if WORKERS_FOLDER_VARIABLE not in os.environ:
            return generate_latest(self.registry), CONTENT_TYPE_LATEST
        every_worker = CollectorRegistry()
        multiprocess.MultiProcessCollector(every_worker)
        return generate_latest(every_worker), CONTENT_TYPE_LATEST

    @staticmethod
    def worker_stopped() -> None:
        """Drops this worker's live gauges (queue depth, readiness) from the sums of the others."""
        if WORKERS_FOLDER_VARIABLE in os.environ:
            multiprocess.mark_process_dead(os.getpid())


class LatencyWindow:
    """Durations of the most recent requests, for cheap percentiles in /health."""

    def __init__(self, size: int):
        self._durations: deque[float] = deque(maxlen=size)

    def add(self, seconds: float) -> None:
        self._durations.append(seconds)

    def summary(self) -> dict[str, float | int | None]:
        if not self._durations:
            return {"count": 0, "p50_ms": None, "p95_ms": None, "p99_ms": None}
        p50, p95, p99 = np.percentile(np.fromiter(self._durations, float), [50, 95, 99]) * 1000.0
        return {"count": len(self._durations), "p50_ms": float(p50), "p95_ms": float(p95), "p99_ms": float(p99)}


class HttpMetricsMiddleware:
    """Counts every HTTP response by route template and status, and times it.

    Routes are labelled by their template (/v2/models/{model_name}/infer), never the raw path,
    and methods by name only for the standard ones, so that the label set stays small whatever
    clients send. Requests that match the
    `windowed_routes` and succeed also feed the /health latency window.
    """

    def __init__(
        self,
        app: ASGIApp,
        metrics: Metrics,
        window: LatencyWindow,
        windowed_routes: set[str],
        static_routes: set[str] = frozenset(),
    ):
        self.app = app
        self.metrics = metrics
        self.window = window
        self.windowed_routes = windowed_routes
        self.static_routes = static_routes  # paths without parameters, for answers given before routing

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500  # what the client sees if the app raises before answering

        async def send_and_record(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_and_record)
        finally:
            route = self._route_template(scope)
            elapsed = time.perf_counter() - started
            method = scope["method"] if scope["method"] in HTTP_METHODS else "other"
            self.metrics.requests.labels(method, route, str(status)).inc()
            self.metrics.request_latency.labels(route).observe(elapsed)
            if route in self.windowed_routes and 200 <= status < 300:
                self.window.add(elapsed)

    def _route_template(self, scope: Scope) -> str:
        route = scope.get("route")  # set by the router once it has matched
        if route is not None and isinstance(getattr(route, "path", None), str):
            return route.path
        endpoint = scope.get("endpoint")
        for candidate in getattr(scope.get("app"), "routes", ()):
            if getattr(candidate, "endpoint", None) is endpoint and endpoint is not None:
                return candidate.path
        # Not routed (e.g. a 413 from the body limit): a known static path is still a safe label.
        return scope["path"] if scope["path"] in self.static_routes else "unmatched"
