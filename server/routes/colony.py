"""/api/colony and /healthz: one status summary of the whole colony."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

from fastapi import APIRouter

from schemas.api import ColonyOut, HealthOut, JobCounts, RobotOut
from server import crud
from server.deps import SessionDep, WorkersDep
from server.routes.runs import aware, run_out

router = APIRouter(tags=["colony"])


def _version() -> str:
    try:
        return version("evocolony")
    except PackageNotFoundError:
        return "unknown"


@router.get("/healthz", response_model=HealthOut)
def healthz() -> HealthOut:
    return HealthOut(version=_version())


@router.get("/api/colony", response_model=ColonyOut)
def colony(session: SessionDep, workers: WorkersDep) -> ColonyOut:
    """Runs by status, the active runs, job counts, workers and robots."""
    active = crud.list_runs(session, statuses=("queued", "running", "paused"), limit=1000)
    return ColonyOut(
        runs=crud.count_runs_by_status(session),
        active=[run_out(r) for r in active],
        jobs=JobCounts(**crud.job_counts(session)),
        workers=workers,
        robots=[
            RobotOut(
                id=r.id,
                status=r.status,
                controller_sha256=r.controller_sha256,
                last_seen=aware(r.last_seen) or r.last_seen,
            )
            for r in crud.list_robots(session)
        ],
    )
