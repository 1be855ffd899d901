"""Prometheus metrics at GET /metrics: live colony state read at scrape time, HTTP latency.

One CollectorRegistry per app (tests build many apps in one process). Most figures are read
from state the server already keeps, so they cannot drift from the REST API: runs, generations
and evaluations from the store, workers from the dispatcher, robots and trace samples from the
robot service, job totals from `Scheduler.totals()` (docs/operations.md).
"""

from __future__ import annotations

import time
from collections.abc import Iterator

from fastapi import FastAPI, Response
from prometheus_client import CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import func, select
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.core.models import Run

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
RUN_STATUSES = ("queued", "running", "paused", "completed", "failed", "cancelled")


class ColonyCollector(Collector):
    """Reads the app's live state at each scrape; absent parts (no zenoh) read as zero."""

    def __init__(self, app: FastAPI) -> None:
        self._app = app

    def collect(self) -> Iterator[Metric]:
        state = self._app.state
        manager = getattr(state, "manager", None)
        if manager is None:  # lifespan not started (or over): nothing live to report
            return
        by_status = {s: 0 for s in RUN_STATUSES}
        with manager.sessions() as db:
            for status, count in db.execute(select(Run.status, func.count()).group_by(Run.status)):
                by_status[str(status)] = int(count)
            generations, evaluations = db.execute(
                select(
                    func.coalesce(func.sum(Run.generation), 0),
                    func.coalesce(func.sum(Run.evaluations), 0),
                )
            ).one()
        runs = GaugeMetricFamily("colony_runs", "Runs by status", labels=["status"])
        for status, count in by_status.items():
            runs.add_metric([status], count)
        yield runs
        yield GaugeMetricFamily(
            "colony_active_runs",
            "Runs evolving now (running)",
            value=by_status["running"],
        )
        yield CounterMetricFamily(
            "colony_generations", "Generations committed over all runs", value=int(generations)
        )
        yield CounterMetricFamily(
            "colony_evaluations",
            "Controllers evaluated over all runs (each over `trials` trials)",
            value=int(evaluations),
        )
        pending = GaugeMetricFamily(
            "colony_jobs", "Jobs of the generations in flight by status", labels=["status"]
        )
        for status, count in manager.scheduler.counts().items():
            pending.add_metric([status], count)
        yield pending
        totals = manager.scheduler.totals()
        for name, meaning in (
            ("leased", "Jobs leased"),
            ("done", "Job results accepted"),
            ("requeued", "Leases returned to pending (expired, worker gone, evaluation failed)"),
            (
                "duplicates_dropped",
                "Results dropped: job already done, or its run or generation over",
            ),
        ):
            yield CounterMetricFamily(f"colony_jobs_{name}", meaning, value=totals[name])
        dispatcher = getattr(state, "dispatcher", None)
        yield CounterMetricFamily(
            "colony_malformed_messages",
            "Worker messages dropped as malformed",
            value=dispatcher.malformed if dispatcher is not None else 0,
        )
        spot = manager.scheduler.spot_totals()
        for name, meaning in (
            ("individuals_checked", "Individuals of worker results re-evaluated (spot-checks)"),
            ("robot_steps_checked", "Robot-steps the spot-checks simulated"),
            ("mismatches", "Spot-checks a worker's result failed (each quarantined it)"),
        ):
            yield CounterMetricFamily(f"colony_spot_check_{name}", meaning, value=spot[name])
        yield GaugeMetricFamily(
            "colony_workers_quarantined",
            "Workers quarantined after a failed spot-check (for the server's life)",
            value=len(manager.scheduler.quarantined()),
        )
        workers = manager.scheduler.workers()
        alive = GaugeMetricFamily("colony_workers", "Simulation workers by state", labels=["state"])
        for worker_state in ("idle", "busy", "gone"):
            alive.add_metric([worker_state], sum(w.state == worker_state for w in workers))
        yield alive
        robots = getattr(state, "robots", None)
        listed = robots.robots() if robots is not None else []
        online = sum(r.online for r in listed)
        yield GaugeMetricFamily("colony_robots_online", "Robots with a live zenoh token", online)
        yield CounterMetricFamily(
            "colony_stuck_events",
            "Stuck requests received from robots",
            value=sum(r.stuck_events for r in listed),
        )
        yield CounterMetricFamily(
            "colony_trace_samples",
            "Trace samples stored since the server started",
            value=robots.traces_received if robots is not None else 0,
        )


def route_template(scope: Scope) -> str:
    """The matched route's path template (/api/runs/{run_id}), never the raw path.

    The router records the route it matched in the (shared) scope before the endpoint runs.
    """
    route = scope.get("route")
    path = getattr(route, "path", None)
    return str(path) if path is not None else "unmatched"


class LatencyMiddleware:
    """HTTP latency to the response's headers by method, route template and status."""

    def __init__(self, app: ASGIApp, histogram: Histogram) -> None:
        self.app = app
        self._histogram = histogram

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = {"code": 500}
        observed = False

        def observe() -> None:
            nonlocal observed
            if not observed:
                observed = True
                route = route_template(scope)
                self._histogram.labels(scope["method"], route, str(status["code"])).observe(
                    time.perf_counter() - started
                )

        async def timed_send(message: Message) -> None:
            if message["type"] == "http.response.start":
                status["code"] = int(message["status"])
                observe()
            await send(message)

        try:
            await self.app(scope, receive, timed_send)
        finally:
            observe()


def install(app: FastAPI) -> CollectorRegistry:
    """Give `app` its registry, the colony collector and the latency middleware."""
    registry = CollectorRegistry()
    registry.register(ColonyCollector(app))
    histogram = Histogram(
        "colony_http_request_duration_seconds",
        "HTTP request latency to the response headers",
        ["method", "route", "status"],
        buckets=LATENCY_BUCKETS,
        registry=registry,
    )
    app.add_middleware(LatencyMiddleware, histogram=histogram)

    @app.get("/metrics", include_in_schema=False)
    def metrics() -> Response:
        return Response(generate_latest(registry), media_type=CONTENT_TYPE)

    return registry
