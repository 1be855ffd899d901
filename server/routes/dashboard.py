"""The browser dashboard: the page at `/`, its static files, `GET /api/events` (SSE), and the
API's Swagger UI at `/docs`.

The event stream polls the store, the dispatcher and the robot service every `POLL_S` and sends
only what changed, so an idle colony costs one small query per tick and no bytes on the wire.
Each stream ends after `STREAM_S` (the browser's EventSource reconnects after `RETRY_MS`,
resuming after its `Last-Event-ID`): uvicorn waits for open responses before it shuts down,
and nothing tells an endless stream that the server is stopping, so a bounded one keeps a
shutdown with open dashboards short.
"""

from __future__ import annotations

import json
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated, Any

import anyio
import anyio.to_thread
from fastapi import APIRouter, Header, HTTPException, Query, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, StreamingResponse
from sqlalchemy import select

from server.core.models import Generation, Run
from server.robots.service import RobotService
from server.routes.deps import get_workers
from server.routes.runs import run_outs
from server.runs.lifecycle import RunManager

router = APIRouter(tags=["dashboard"])

STATIC = Path(__file__).resolve().parent.parent / "static"
SWAGGER_UI = "/static/vendor/swagger-ui"
POLL_S = 0.5
"""Seconds between two looks at the store; a generation shows up at most this late."""
STREAM_S = 10.0
"""Lifetime of one event stream before the browser reconnects (bounds a shutdown's wait)."""
RETRY_MS = 1000
"""The reconnection delay sent to EventSource."""
RUNS_LIMIT = 100
"""The newest runs the stream follows for status changes."""


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})


@router.get("/static/{path:path}", include_in_schema=False)
def static(path: str) -> FileResponse:
    """Files under server/static only (no CDN: lab networks are often offline)."""
    target = (STATIC / path).resolve()
    if not target.is_relative_to(STATIC) or not target.is_file():
        raise HTTPException(404, detail=f"no static file {path}")
    return FileResponse(target, headers={"Cache-Control": "no-cache"})


@router.get("/docs", include_in_schema=False)
def docs() -> HTMLResponse:
    """Swagger UI from vendored files: FastAPI's default page loads it from a CDN, blank offline.
    No validator badge either: it would send the schema to an online validator."""
    return get_swagger_ui_html(
        openapi_url="/openapi.json",
        title="EvoColony API",
        swagger_js_url=f"{SWAGGER_UI}/swagger-ui-bundle.js",
        swagger_css_url=f"{SWAGGER_UI}/swagger-ui.css",
        swagger_favicon_url=f"{SWAGGER_UI}/favicon-32x32.png",
        swagger_ui_parameters={"validatorUrl": None},
    )


def sse(event: str, data: object, event_id: int | None = None) -> str:
    """One server-sent event; `data` as one line of JSON."""
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def _finite(value: float | None) -> float | None:
    """JSON has no NaN or infinity; a statistic that is not finite is sent as null."""
    return value if value is not None and math.isfinite(value) else None


class Watch:
    """What one stream has sent so far; `poll()` returns the events of what changed since."""

    def __init__(self, request: Request, run_id: int | None, after: int) -> None:
        self._request = request
        self._run_id = run_id
        self._after = after
        self._runs: dict[int, tuple[object, ...]] = {}
        self._workers: object = None
        self._robots: object = None

    def poll(self) -> list[str]:
        manager: RunManager = self._request.app.state.manager
        events: list[str] = []
        # one read snapshot, generations first: a run that reads completed follows all of them
        with manager.sessions() as session:
            if self._run_id is not None:
                rows = session.execute(
                    select(
                        Generation.generation,
                        Generation.best,
                        Generation.mean,
                        Generation.worst,
                        Generation.nan_count,
                    )
                    .where(Generation.run_id == self._run_id, Generation.generation > self._after)
                    .order_by(Generation.generation)
                )
                for g, best, mean, worst, nan_count in rows:
                    stats = {"best": _finite(best), "mean": _finite(mean), "worst": _finite(worst)}
                    data = {
                        "run_id": self._run_id,
                        "generation": g,
                        **stats,
                        "nan_count": nan_count,
                    }
                    events.append(sse("generation", data, event_id=g))
                    self._after = g
            progress = select(
                Run.id,
                Run.status,
                Run.generation,
                Run.best_fitness,
                Run.evaluations,
                Run.error,
                Run.started_at,
                Run.finished_at,
                Run.champion_sha256,
            )
            refused = manager.write_refused()
            changed: list[Run] = []
            for run_id, *key in session.execute(progress.order_by(Run.id.desc()).limit(RUNS_LIMIT)):
                seen = (*key, refused.get(run_id))
                if self._runs.get(run_id) != seen:
                    self._runs[run_id] = seen
                    run = session.get(Run, run_id)  # the whole row (config) only when it changed
                    if run is not None:
                        changed.append(run)
            for out in run_outs(session, changed, refused):
                events.append(sse("run", out.model_dump(mode="json")))
        workers = [w.model_dump(mode="json") for w in get_workers(self._request)]
        if workers != self._workers:
            self._workers = workers
            events.append(sse("workers", workers))
        robots = self._robot_snapshot()
        if robots != self._robots:
            self._robots = robots
            events.append(sse("robots", robots))
        return events

    def _robot_snapshot(self) -> dict[str, Any]:
        """Every robot's detail and its controller's field statistics, or why there are none."""
        service: RobotService | None = getattr(self._request.app.state, "robots", None)
        if service is None:
            return {"available": False, "robots": []}
        robots: list[dict[str, Any]] = []
        for summary in service.robots():
            detail = service.robot(summary.id).model_dump(mode="json")
            sha = summary.controller_sha256
            stats = service.field_stats(sha) if sha else None
            detail["field"] = None if stats is None else stats.model_dump(mode="json")
            robots.append(detail)
        return {"available": True, "robots": robots}


@router.get(
    "/api/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "server-sent events"}},
)
async def events(
    request: Request,
    run: Annotated[int | None, Query(ge=0, description="stream this run's generations")] = None,
    last_event_id: Annotated[str | None, Header()] = None,
) -> StreamingResponse:
    """Run progress as server-sent events: `run` (a RunOut, at once and whenever its status or
    progress changes), `generation` (best, mean, worst of each committed generation of `run`;
    its id is the generation, so a reconnecting EventSource resumes after the last one),
    `workers` and `robots` (snapshots when they change)."""
    after = -1
    if last_event_id is not None:
        try:
            after = int(last_event_id)
        except ValueError as exc:
            raise HTTPException(422, detail="Last-Event-ID: must be a generation number") from exc
    watch = Watch(request, run, after)

    async def stream() -> AsyncIterator[str]:
        yield f"retry: {RETRY_MS}\n\n"
        deadline = anyio.current_time() + STREAM_S
        while True:
            changes = await anyio.to_thread.run_sync(watch.poll)
            if changes:
                yield "".join(changes)  # one write per tick
            if anyio.current_time() >= deadline:
                return
            await anyio.sleep(POLL_S)

    return StreamingResponse(
        stream(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
