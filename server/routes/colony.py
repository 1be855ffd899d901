"""/api/colony and /healthz: one status summary of the whole colony."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse

from schemas.api import ColonyOut, HealthOut, JobCounts
from schemas.robots import ColonyMapOut
from server.robots.map import PATH_SAMPLES, colony_map
from server.robots.registry import robot_summaries
from server.robots.service import RobotService
from server.routes.deps import SessionDep, WorkersDep
from server.routes.runs import run_outs
from server.runs import crud
from server.runs.lifecycle import RunManager

router = APIRouter(tags=["colony"])


def _version() -> str:
    try:
        return version("evocolony")
    except PackageNotFoundError:
        return "unknown"


@router.get(
    "/healthz",
    response_model=HealthOut,
    responses={
        503: {
            "model": HealthOut,
            "description": "a loop the server needs stopped, or the store refuses writes",
        }
    },
)
def healthz(request: Request) -> HealthOut | JSONResponse:
    """ok while every loop the server needs runs (the run manager's writer, the zenoh
    dispatcher, the in-process evaluators) and the store takes the manager's writes;
    unhealthy (a restart may help) when a loop stopped, else degraded (the store refuses
    writes, e.g. a full disk: runs are paused until it takes them again)."""
    state = request.app.state
    loops = {name: getattr(state, name, None) for name in ("manager", "dispatcher", "executor")}
    stopped = [name for name, part in loops.items() if part is not None and not part.alive()]
    manager: RunManager | None = loops["manager"]
    refused = manager.write_refused() if manager is not None else {}
    problems = sorted(set(refused.values()))
    status = "unhealthy" if stopped else "degraded" if problems else "ok"
    health = HealthOut(version=_version(), status=status, stopped=stopped, problems=problems)
    if status != "ok":
        return JSONResponse(status_code=503, content=health.model_dump())
    return health


@router.get("/api/colony", response_model=ColonyOut)
def colony(request: Request, session: SessionDep, workers: WorkersDep) -> ColonyOut:
    """Runs by status, the active runs, job counts, workers and robots."""
    robots: RobotService | None = getattr(request.app.state, "robots", None)
    active = crud.list_runs(session, statuses=("queued", "running", "paused"), limit=1000)
    refused = request.app.state.manager.write_refused()
    return ColonyOut(
        runs=crud.count_runs_by_status(session),
        active=run_outs(session, active, refused),
        jobs=JobCounts(**request.app.state.manager.scheduler.counts()),
        workers=workers,
        robots=robot_summaries(
            session,
            robots.is_online if robots else _offline,
            (robots.settings if robots else request.app.state.manager.settings).replacement,
        ),
    )


@router.get("/api/colony/map", response_model=ColonyMapOut)
def colony_map_view(
    request: Request,
    session: SessionDep,
    samples: Annotated[
        int, Query(ge=1, le=36_000, description="recent poses per robot (10 a second)")
    ] = PATH_SAMPLES,
) -> ColonyMapOut:
    """The lab maze (the server's `maze` setting) and each robot's newest pose, recent path
    and the stuck events on it, for the Colony page's map."""
    robots: RobotService | None = getattr(request.app.state, "robots", None)
    maze = request.app.state.manager.settings.maze
    return colony_map(session, maze, robots.is_online if robots else _offline, samples)


def _offline(_robot_id: str) -> bool:
    """Without the robot service (no zenoh) no robot is online."""
    return False
