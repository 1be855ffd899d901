"""GET /metrics: Prometheus text with live colony state; counters move after a run."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import uvicorn
from fastapi import FastAPI
from prometheus_client.parser import text_string_to_metric_families

from schemas.run import RunConfig
from schemas.wire import Result
from server.app import create_app
from server.core.db import make_engine, upgrade
from server.core.settings import Settings
from server.runs.lifecycle import RunManager
from tests.helpers import eventually

SMALL = {"population": 8, "generations": 3, "steps": 10, "job_size": 4}


@contextmanager
def serve(app: FastAPI) -> Iterator[httpx.Client]:
    """The app on real uvicorn on a free port; a client for it."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        assert eventually(lambda: server.started or not thread.is_alive())
        assert server.started, "uvicorn did not start"
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as client:
            yield client
    finally:
        server.should_exit = True
        thread.join(timeout=30)


def scrape(client: httpx.Client) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    response = client.get("/metrics")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(response.text)
        for s in family.samples
    }


def test_metrics_names_and_counters_move_after_a_run(tmp_path: Path) -> None:
    settings = Settings(db_url=f"sqlite:///{tmp_path / 'c.db'}", zenoh=False, executors=2)
    with serve(create_app(settings)) as client:
        before = scrape(client)
        names = {name for name, _ in before}
        for expected in (
            "colony_runs",
            "colony_active_runs",
            "colony_generations_total",
            "colony_evaluations_total",
            "colony_jobs",
            "colony_jobs_leased_total",
            "colony_jobs_done_total",
            "colony_jobs_requeued_total",
            "colony_jobs_duplicates_dropped_total",
            "colony_workers",
            "colony_robots_online",
            "colony_stuck_events_total",
            "colony_trace_samples_total",
        ):
            assert expected in names, expected
        assert before[("colony_generations_total", ())] == 0
        run = client.post("/api/runs", json=SMALL).json()
        assert eventually(
            lambda: client.get(f"/api/runs/{run['id']}").json()["status"] == "completed"
        )
        after = scrape(client)
    assert after[("colony_generations_total", ())] == SMALL["generations"]
    assert after[("colony_evaluations_total", ())] == SMALL["generations"] * SMALL["population"]
    # one job per live worker (two executor threads) a generation, and so a champion's stage
    jobs = (SMALL["generations"] + 2) * 2
    assert after[("colony_jobs_done_total", ())] == jobs
    assert after[("colony_jobs_leased_total", ())] >= jobs
    assert after[("colony_jobs_duplicates_dropped_total", ())] == 0
    assert after[("colony_runs", (("status", "completed"),))] == 1
    # latency by route template, never by raw path
    routes = {dict(labels).get("route") for name, labels in after if name.endswith("_count")}
    assert "/api/runs/{run_id}" in routes
    assert f"/api/runs/{run['id']}" not in routes
    key = (
        "colony_http_request_duration_seconds_count",
        (("method", "POST"), ("route", "/api/runs"), ("status", "201")),
    )
    assert after[key] == 1


def test_each_app_has_its_own_registry(tmp_path: Path) -> None:
    """Two apps in one process: no duplicate-timeseries error, separate latency counts."""
    first = create_app(Settings(db_url=f"sqlite:///{tmp_path / 'a.db'}", zenoh=False))
    second = create_app(Settings(db_url=f"sqlite:///{tmp_path / 'b.db'}", zenoh=False))
    with serve(first) as a, serve(second) as b:
        a.get("/healthz")
        a.get("/healthz")
        b.get("/healthz")
        key = (
            "colony_http_request_duration_seconds_count",
            (("method", "GET"), ("route", "/healthz"), ("status", "200")),
        )
        assert scrape(a)[key] == 2
        assert scrape(b)[key] == 1


def test_scheduler_totals_count_leases_results_requeues_and_duplicates(tmp_path: Path) -> None:
    """The scheduler keeps its own running totals; /metrics reads them at scrape time."""
    engine = make_engine(f"sqlite:///{tmp_path / 'q.db'}")
    upgrade(engine)
    # a result of zero fitness stands in for evaluation: no spot-checks (test_spotcheck.py)
    settings = Settings(db_url="unused", lease_unknown_seconds=0.5, spot_checks=0)
    manager = RunManager(engine, settings)
    config = RunConfig(population=8, generations=2, steps=10, trials=1, job_size=4)
    try:
        manager.create_run(config)
        scheduler = manager.scheduler
        assert scheduler.totals() == {
            "leased": 0,
            "done": 0,
            "requeued": 0,
            "duplicates_dropped": 0,
        }
        first, second = scheduler.lease("a"), scheduler.lease("b")
        assert first is not None and second is not None
        result = Result(
            key=second.key,
            worker="b",
            start=second.start,
            stop=second.stop,
            fitness=np.zeros((1, 4)),
            components=np.zeros((1, 4, 1, 4)),
            descriptors=np.zeros((1, 4, 4)),
        )
        assert scheduler.settle(result).accepted is True
        assert scheduler.settle(result).accepted is False  # duplicate
        again = scheduler.lease("a")  # asking again returns what "a" held, then leases it
        assert again is not None and again.key == first.key
        deadline = scheduler.next_deadline()
        assert deadline is not None
        assert eventually(lambda: scheduler.now() >= deadline, timeout=10.0)
        assert scheduler.expire() == 1
        assert scheduler.totals() == {
            "leased": 3,
            "done": 1,
            "requeued": 2,
            "duplicates_dropped": 1,
        }
    finally:
        engine.dispose()
