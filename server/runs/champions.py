"""Champions of runs, and the store's reads of a run's best controller and archive.

A run completes with its validated champion (`evorobotics.evolution.champion`: the final
population's best on the run's validation set), stored in `controllers` and named by
`runs.champion_sha256` (`store_champion`) in the transaction that writes the last generation.
It is chosen by jobs like a generation's (`server.runs.choosing`), never simulated here.
"""

from __future__ import annotations

import logging

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from evorobotics.document import ControllerDocument
from evorobotics.evolution import RunLoop, best_document
from evorobotics.strategies import Archive, traits
from schemas.run import RunConfig
from server.core.errors import NotFoundError
from server.core.models import Run
from server.runs import crud

log = logging.getLogger(__name__)

ARCHIVES_KEPT = 8
"""Replayed archives `Champions.archive` keeps (a dashboard polls the same run's)."""


class Champions:
    """Reads a run's best controller and archive from the store."""

    def __init__(self, sessions: sessionmaker[Session]) -> None:
        self._sessions = sessions
        self._archives: dict[tuple[int, int], Archive] = {}
        """(run id, generations) -> its archive replayed (`archive`), oldest first."""

    def archive(self, run_id: int) -> tuple[int, RunConfig, Archive]:
        """(generations, config, archive) of a map-elites, cma-me or novelty run after its
        committed generations, replayed from the store (about 1 s per 350 generations; the
        last ARCHIVES_KEPT are kept). NotFoundError for another strategy or before its first
        committed generation."""
        with self._sessions() as session:
            run = crud.find_run(session, run_id=run_id)
            config = RunConfig.model_validate_json(run.config)
            if not traits(config).archive:
                raise NotFoundError(f"run {run_id}'s strategy {config.strategy} keeps no archive")
            g = run.generation
            if g == 0:
                raise NotFoundError(f"run {run_id} has no committed generation yet")
            cached = self._archives.get((run_id, g))
            if cached is not None:
                return g, config, cached
            history = crud.history(session, run_id=run_id, generations=g)
        archive = RunLoop.resume(config, history).archive()
        assert archive is not None  # its strategy keeps one
        self._archives[(run_id, g)] = archive
        while len(self._archives) > ARCHIVES_KEPT:
            self._archives.pop(next(iter(self._archives)))
        return g, config, archive

    def best(self, run_id: int) -> ControllerDocument:
        """The run's best controller, read from the store (nothing is written): a completed
        run's validated champion (with `validation`), any other run's training rank 0 of its
        latest committed generation; NotFoundError before its first committed generation."""
        with self._sessions() as session:
            run = crud.find_run(session, run_id=run_id)
            stored = crud.champion(session, run=run)
            if stored is not None:
                return ControllerDocument.from_json(stored.document)
            document = _best(session, run, RunConfig.model_validate_json(run.config))
        if document is None:
            raise NotFoundError(f"run {run_id} has no completed generation yet")
        return document


def store_champion(
    session: Session, run: Run, config: RunConfig, document: ControllerDocument
) -> str:
    """Store a finished run's champion `document` and name it on the run, so it is fetched
    and pushed by its sha256 after any restart; its sha256. It replaces a document of the
    same sha256 that a push stored before without the `validation` member."""
    crud.put_controller(
        session,
        sha256=document.sha256,
        document=document.to_json(),
        run_id=run.id,
        generation=config.generations - 1,
        fitness=document.fitness,
        replace=True,
    )
    run.champion_sha256 = document.sha256
    return document.sha256


def _best(session: Session, run: Run, config: RunConfig) -> ControllerDocument | None:
    """Training rank 0 of the latest committed generation."""
    latest = crud.latest_generation(session, run_id=run.id)
    if latest is None:
        return None
    found, genomes = crud.ranked(session, run_id=run.id, generation=latest.generation, rank=0)
    return best_document(
        config,
        genomes,
        found.fitness[:1],
        np.array([0]),
        generation=latest.generation,
        run=run.id,
    )
