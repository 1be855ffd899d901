"""Annotated dependencies of the routes: the manager, a read session, the worker table, the
reports' cache, the study service."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from schemas.api import WorkerOut
from server.runs.lifecycle import RunManager
from server.studies.evaluation import Evaluations
from server.studies.service import StudyService


def get_manager(request: Request) -> RunManager:
    manager: RunManager = request.app.state.manager
    return manager


def get_session(request: Request) -> Iterator[Session]:
    manager: RunManager = request.app.state.manager
    with manager.sessions() as session:
        yield session


ManagerDep = Annotated[RunManager, Depends(get_manager)]
SessionDep = Annotated[Session, Depends(get_session)]


def get_workers(request: Request) -> list[WorkerOut]:
    """The scheduler's worker table (zenoh workers and in-process evaluators), by name."""
    manager: RunManager = request.app.state.manager
    quarantined = manager.scheduler.quarantined()
    return [
        WorkerOut(
            name=w.name,
            host=w.host,
            state=w.state,
            jobs_done=w.jobs_done,
            evaluations=w.evaluations,
            late=w.late,
            robot_steps_per_s=w.robot_steps_per_s,
            last_seen=datetime.fromtimestamp(w.last_seen, UTC),
            quarantined=w.name in quarantined,
            quarantine_reason=quarantined.get(w.name),
        )
        for w in manager.scheduler.workers()
    ]


WorkersDep = Annotated[list[WorkerOut], Depends(get_workers)]


def get_evaluations(request: Request) -> Evaluations:
    """The app's reports (exploration reports and robustness maps of stored controllers)."""
    evaluations: Evaluations = request.app.state.evaluations
    return evaluations


EvaluationsDep = Annotated[Evaluations, Depends(get_evaluations)]


def get_studies(request: Request, manager: ManagerDep, evaluations: EvaluationsDep) -> StudyService:
    """The app's study service, made on first use for the app's manager."""
    service: StudyService | None = getattr(request.app.state, "studies", None)
    if service is None or service.manager is not manager:
        service = StudyService(manager, evaluations)
        request.app.state.studies = service
    return service


StudiesDep = Annotated[StudyService, Depends(get_studies)]
