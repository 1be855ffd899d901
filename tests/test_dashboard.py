"""The dashboard over HTTP: the page and its files, the event stream of a running run, figures.

Real uvicorn on a free port, a temporary SQLite file, in-process evaluation (no zenoh).
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable, Iterator
from typing import Any

import httpx
import pytest

from server.routes.dashboard import sse
from tests.helpers import QUICK, Served, eventually, serve

WAIT = 60.0
SLOW = {"population": 12, "generations": 40, "steps": 60, "job_size": 4}
"""Long enough to be running while a stream is read (about 0.1 s a generation)."""


def read_events(
    client: httpx.Client,
    path: str,
    until: Callable[[list[tuple[str, Any]]], bool],
    headers: dict[str, str] | None = None,
    timeout: float = WAIT,
) -> list[tuple[str, Any]]:
    """Parse server-sent events until `until` holds, reconnecting like EventSource (with the
    last event id) when a stream ends."""
    events: list[tuple[str, Any]] = []
    headers = dict(headers or {})
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with client.stream("GET", path, headers=headers, timeout=timeout) as response:
            assert response.status_code == 200
            assert response.headers["content-type"].startswith("text/event-stream")
            kind, data = "message", ""
            for line in response.iter_lines():
                if line.startswith("id: "):
                    headers["Last-Event-ID"] = line[4:]
                elif line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: "):
                    data = line[6:]
                elif line == "" and data:
                    events.append((kind, json.loads(data)))
                    kind, data = "message", ""
                    if until(events):
                        return events
    raise AssertionError(f"the stream did not deliver in {timeout} s: {events[-5:]}")


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    with serve(tmp_path_factory.mktemp("dashboard")) as s:
        yield s


@pytest.fixture
def client(served: Served) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=served.url, timeout=30) as c:
        yield c


def finished(client: httpx.Client, run_id: int) -> bool:
    return bool(client.get(f"/api/runs/{run_id}").json()["status"] == "completed")


def test_root_serves_the_page_and_its_files(client: httpx.Client) -> None:
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "<title>EvoColony</title>" in page.text and 'id="curve"' in page.text
    for path in ("/static/app.js", "/static/style.css", "/static/vendor/uplot/uPlot.iife.min.js"):
        response = client.get(path)
        assert response.status_code == 200, path
        assert len(response.content) > 1000, path
    assert "MIT" in client.get("/static/vendor/uplot/LICENSE").text
    assert client.get("/static/missing.js").status_code == 404
    assert client.get("/static/%2e%2e/app.py").status_code == 404  # nothing outside static/


def test_api_docs_page_loads_only_files_this_server_serves(client: httpx.Client) -> None:
    page = client.get("/docs")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "://" not in page.text  # no CDN: lab networks are often offline
    assets = re.findall(r'(?:src|href)="([^"]+)"', page.text)
    assert len(assets) == 3, assets
    for path in assets:
        response = client.get(path)
        assert response.status_code == 200, path
        assert len(response.content) > 500, path
    assert "Apache License" in client.get("/static/vendor/swagger-ui/LICENSE").text
    assert "url: '/openapi.json'" in page.text
    assert client.get("/openapi.json").json()["info"]["title"] == "EvoColony"
    assert client.get("/redoc").status_code == 404


def test_stream_yields_generations_of_a_running_run(client: httpx.Client) -> None:
    run_id = client.post("/api/runs", json=SLOW).json()["id"]

    def got_generation(events: list[tuple[str, Any]]) -> bool:
        # one poll carries its events in any order: wait for every kind asserted on below
        seen_run = any(kind == "run" and data["id"] == run_id for kind, data in events)
        kinds = {kind for kind, _ in events}
        return seen_run and {"generation", "workers", "robots"} <= kinds

    events = read_events(client, f"/api/events?run={run_id}", got_generation)
    runs = [data for kind, data in events if kind == "run" and data["id"] == run_id]
    assert runs and runs[0]["config"]["population"] == SLOW["population"]
    assert runs[0]["status"] in ("queued", "running")  # streamed while it evolves
    first = next(data for kind, data in events if kind == "generation")
    assert first["run_id"] == run_id and first["generation"] == 0
    assert first["worst"] <= first["mean"] <= first["best"]
    snapshots = {kind: data for kind, data in events if kind in ("workers", "robots")}
    assert snapshots["workers"] == []  # in-process evaluation: no zenoh worker
    assert snapshots["robots"] == {"available": False, "robots": []}

    # the stream reports the status change, and each generation once, in order
    def completed(events: list[tuple[str, Any]]) -> bool:
        return any(
            k == "run" and d["id"] == run_id and d["status"] == "completed" for k, d in events
        )

    events = read_events(client, f"/api/events?run={run_id}", completed)
    generations = [d["generation"] for k, d in events if k == "generation"]
    assert generations == list(range(SLOW["generations"]))
    stored = client.get(f"/api/runs/{run_id}/generations").json()
    last = next(d for k, d in reversed(events) if k == "generation")
    assert last["best"] == stored[-1]["best"] and last["mean"] == stored[-1]["mean"]


def test_stream_resumes_after_last_event_id(client: httpx.Client) -> None:
    run_id = client.post("/api/runs", json=QUICK).json()["id"]
    assert eventually(lambda: finished(client, run_id))

    def has_generation(events: list[tuple[str, Any]]) -> bool:
        return any(kind == "generation" for kind, _ in events)

    events = read_events(
        client, f"/api/events?run={run_id}", has_generation, headers={"Last-Event-ID": "0"}
    )
    assert [d["generation"] for k, d in events if k == "generation"] == [1]
    bad = client.get(f"/api/events?run={run_id}", headers={"Last-Event-ID": "x"})
    assert bad.status_code == 422


def test_best_figures_are_pngs_cached_by_sha(client: httpx.Client) -> None:
    run_id = client.post("/api/runs", json=QUICK).json()["id"]
    assert eventually(lambda: finished(client, run_id))
    for figure in ("network", "paths"):
        response = client.get(f"/api/runs/{run_id}/best/{figure}.png")
        assert response.status_code == 200, response.text
        assert response.headers["content-type"] == "image/png"
        assert response.content.startswith(b"\x89PNG\r\n\x1a\n")
        etag = response.headers["etag"]
        sha = client.get(f"/api/runs/{run_id}/best").json()["sha256"]
        assert sha in etag
        again = client.get(f"/api/runs/{run_id}/best/{figure}.png", headers={"If-None-Match": etag})
        assert again.status_code == 304
        assert client.get(f"/api/runs/{run_id}/best/{figure}.png").content == response.content
    assert client.get(f"/api/runs/{run_id}/best/other.png").status_code == 422
    assert client.get("/api/runs/999/best/network.png").status_code == 404


def test_sse_format() -> None:
    assert sse("run", {"id": 1}) == 'event: run\ndata: {"id":1}\n\n'
    assert sse("generation", {"g": 2}, event_id=2) == 'id: 2\nevent: generation\ndata: {"g":2}\n\n'
