"""/api/runs: create runs, follow them, steer their lifecycle."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Body, HTTPException, Path, Query, Response, status
from sqlalchemy.orm import Session

from evorobotics.document import controller_sha256
from evorobotics.evaluate import trial_steps
from evorobotics.strategies import traits
from schemas.api import (
    ArchiveCell,
    ArchiveOut,
    ChampionOut,
    GenerationOut,
    IndividualOut,
    IndividualsOut,
    RunCreate,
    RunOut,
    RunStatus,
)
from schemas.run import RunConfig
from server.core.auth import run_limit_error
from server.core.errors import NotFoundError
from server.core.models import Run, aware
from server.robots.registry import with_colony_gap
from server.routes.deps import ManagerDep, SessionDep
from server.runs import crud

RunId = Annotated[int, Path(ge=0, le=2**63 - 1, description="a run id (64-bit)")]
"""Bounded so an id beyond the database's integers is a 422, not an overflow."""

router = APIRouter(prefix="/api/runs", tags=["runs"])


def run_outs(
    session: Session, runs: Sequence[Run], refused: Mapping[int, str] | None = None
) -> list[RunOut]:
    """The runs as stored, with their best training fitness so far and their champions, read in
    one query each. A run in `refused` (`RunManager.write_refused`: its generation could not be
    written, nor could the pause that follows) shows as paused with the store's error, the state
    the store will show once it accepts writes again."""
    ids = [run.id for run in runs]
    best = crud.best_so_far(session, run_ids=ids)
    champions = crud.champion_documents(session, runs=runs)
    return [_run_out(run, refused, best.get(run.id), champions.get(run.id)) for run in runs]


def run_out(session: Session, run: Run, refused: Mapping[int, str] | None = None) -> RunOut:
    """One run as `run_outs` reports it."""
    return run_outs(session, [run], refused)[0]


def _champion(document: str) -> ChampionOut:
    """The champion's figures from its stored controller document."""
    data = json.loads(document)
    return ChampionOut(
        sha256=data["sha256"],
        training_fitness=data.get("fitness"),
        validation=data.get("validation"),
        test=data.get("test"),
    )


def _run_out(
    run: Run,
    refused: Mapping[int, str] | None,
    best_so_far: float | None,
    champion: str | None,
) -> RunOut:
    config = RunConfig.model_validate_json(run.config)
    created = aware(run.created_at)
    if created is None:
        raise ValueError(f"run {run.id} has no creation time")
    status, error = run.status, run.error
    if refused and run.id in refused and status == "running":
        status, error = "paused", refused[run.id]
    return RunOut(
        id=run.id,
        status=status,  # the manager writes only RunStatus values
        seed=run.seed,
        config=config,
        generation=run.generation,
        generations=config.generations,
        best_fitness=run.best_fitness,
        best_fitness_so_far=best_so_far,
        trial_steps=trial_steps(config),
        evaluations=run.evaluations,
        created_at=created,
        started_at=aware(run.started_at),
        finished_at=aware(run.finished_at),
        error=error,
        name=run.name,
        tags=json.loads(run.tags or "[]"),
        study_id=run.study_id,
        condition=run.condition,
        keeps_archive=traits(config).archive,
        champion=None if champion is None else _champion(champion),
    )


def _run(session: SessionDep, run_id: RunId) -> Run:
    run = crud.get_run(session, run_id=run_id)
    if run is None:
        raise HTTPException(status_code=404, detail=f"no run with id {run_id}")
    return run


@router.post("", status_code=status.HTTP_201_CREATED, response_model=RunOut)
def create_run(
    manager: ManagerDep,
    session: SessionDep,
    body: Annotated[RunCreate | None, Body()] = None,
) -> RunOut:
    """Start a run; every config field is optional and defaults to the paper's experiment;
    `name` and `tags` label it."""
    body = body or RunCreate()
    try:
        config = with_colony_gap(session, body.run_config())
    except NotFoundError as exc:
        raise HTTPException(422, str(exc)) from exc
    refused = run_limit_error(
        config,
        max_population_weights=manager.settings.max_population_weights,
        max_generation_steps=manager.settings.max_generation_steps,
        max_run_steps=manager.settings.max_run_steps,
    )
    if refused is not None:
        raise HTTPException(422, refused)
    run_id = manager.create_run(config, name=body.name, tags=body.tags)
    return run_out(session, _run(session, run_id))


@router.get("", response_model=list[RunOut])
def list_runs(
    manager: ManagerDep,
    session: SessionDep,
    status_: Annotated[list[RunStatus] | None, Query(alias="status")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=2**63 - 1)] = 0,
) -> list[RunOut]:
    """Newest first; `?status=running&status=paused` filters by the stored status."""
    runs = crud.list_runs(session, statuses=status_, limit=limit, offset=offset)
    refused = manager.write_refused()
    return run_outs(session, runs, refused)


@router.get("/{run_id}", response_model=RunOut)
def get_run(manager: ManagerDep, session: SessionDep, run_id: RunId) -> RunOut:
    return run_out(session, _run(session, run_id), manager.write_refused())


@router.get("/{run_id}/generations", response_model=list[GenerationOut])
def list_generations(session: SessionDep, run_id: RunId) -> list[GenerationOut]:
    _run(session, run_id)
    return [
        GenerationOut(
            generation=g.generation, best=g.best, mean=g.mean, worst=g.worst, nan_count=g.nan_count
        )
        for g in crud.list_generations(session, run_id=run_id)
    ]


@router.get("/{run_id}/archive", response_model=ArchiveOut)
def get_archive(manager: ManagerDep, run_id: RunId) -> ArchiveOut:
    """The archive of a map-elites, cma-me or novelty run after its committed generations:
    each elite's two descriptors, fitness and controller sha256; 404 for another strategy."""
    generation, config, archive = manager.archive(run_id)
    spec = config.network_spec
    return ArchiveOut(
        run_id=run_id,
        generation=generation,
        axes=list(config.strategy_settings.axes),
        cells=[
            ArchiveCell(
                descriptors=[float(v) for v in d],
                fitness=float(f) if np.isfinite(f) else None,
                sha256=controller_sha256(spec, genome),
            )
            for d, f, genome in zip(
                archive.descriptors, archive.fitness, archive.genomes, strict=True
            )
        ],
    )


@router.get("/{run_id}/individuals", response_model=IndividualsOut)
def list_individuals(
    session: SessionDep,
    run_id: RunId,
    generation: Annotated[
        int | None, Query(ge=0, le=2**31 - 1, description="default: the latest")
    ] = None,
) -> IndividualsOut:
    """The individuals of a committed generation, fittest first. A generation between
    checkpoints is rebuilt (replayed, its trials simulated again): 503 with Retry-After while
    another is."""
    run = _run(session, run_id)
    if generation is None:
        latest = crud.latest_generation(session, run_id=run_id)
        if latest is None:
            raise HTTPException(404, detail=f"run {run_id} has no completed generation yet")
        generation = latest.generation
    elif generation >= run.generation:
        raise HTTPException(
            404, detail=f"run {run_id} has committed generations 0..{run.generation - 1} only"
        )
    found, genomes = crud.ranked(
        session, run_id=run_id, generation=generation, components=True, exclusive=True
    )
    spec = RunConfig.model_validate_json(run.config).network_spec
    return IndividualsOut(
        run_id=run_id,
        generation=generation,
        individuals=[
            IndividualOut(
                rank=rank,
                index=int(found.index[rank]),
                parent=found.parent_of(rank),
                fitness=found.fitness_of(rank),
                components=[] if found.components is None else found.components[rank].tolist(),
                sha256=controller_sha256(spec, genomes[rank]),
            )
            for rank in range(len(found))
        ],
    )


@router.get(
    "/{run_id}/best",
    response_class=Response,
    responses={200: {"content": {"application/json": {}}, "description": "controller document"}},
)
def best(manager: ManagerDep, run_id: RunId) -> Response:
    """The run's best controller document: a completed run's validated champion (with its
    `validation` member), any other run's training rank 0 of its latest generation."""
    return Response(content=manager.best(run_id).to_json(), media_type="application/json")


def _steer(manager: ManagerDep, session: SessionDep, run_id: RunId, action: str) -> RunOut:
    getattr(manager, action)(run_id)
    session.expire_all()
    return run_out(session, _run(session, run_id), manager.write_refused())


@router.post("/{run_id}/pause", response_model=RunOut)
def pause(manager: ManagerDep, session: SessionDep, run_id: RunId) -> RunOut:
    """running or queued -> paused (jobs in hand still finish; none are handed out)."""
    return _steer(manager, session, run_id, "pause")


@router.post("/{run_id}/resume", response_model=RunOut)
def resume(manager: ManagerDep, session: SessionDep, run_id: RunId) -> RunOut:
    """paused -> running (or queued if it never started)."""
    return _steer(manager, session, run_id, "resume")


@router.post("/{run_id}/cancel", response_model=RunOut)
def cancel(manager: ManagerDep, session: SessionDep, run_id: RunId) -> RunOut:
    """queued, running or paused -> cancelled; its pending jobs are dropped."""
    return _steer(manager, session, run_id, "cancel")


@router.delete("/{run_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_run(manager: ManagerDep, run_id: RunId) -> Response:
    """Delete the run and its generations (cancelled first if live); its controllers stay."""
    manager.delete_run(run_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
