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
from server.core.errors import NotFoundError, UnconfirmedError
from server.core.models import Run
from server.runs import crud
from server.runs.evaluation import repeats_claim

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
        run's validated champion (with `validation`), any other run's best training rank of its
        latest committed generation whose claimed fitness the server's own evaluation repeats
        (`confirmed_document`); NotFoundError before its first committed generation."""
        with self._sessions() as session:
            run = crud.find_run(session, run_id=run_id)
            stored = crud.champion(session, run=run)
            if stored is not None:
                return ControllerDocument.from_json(stored.document)
            config = RunConfig.model_validate_json(run.config)
            return confirmed_document(session, run, config)[1]


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


def confirmed_document(
    session: Session, run: Run, config: RunConfig, rank: int | None = None
) -> tuple[int, ControllerDocument]:
    """(generation, document): the controller of training rank `rank` of the run's latest committed generation, or
    without `rank` of the best rank, only if this process's own evaluation repeats its claimed
    fitness bit for bit (`repeats_claim`): ranks that do not are logged and skipped, so no
    worker crowns a controller by a forged fitness. One evaluation of one individual when the
    claims are true (a few ms), at most the generation's when they are not. NotFoundError
    before the first committed generation or for a rank beyond it; UnconfirmedError when no
    claim asked for holds."""
    latest = crud.latest_generation(session, run_id=run.id)
    if latest is None:
        raise NotFoundError(f"run {run.id} has no completed generation yet")
    g = latest.generation
    found, genomes = crud.ranked(session, run_id=run.id, generation=g)
    if rank is not None and not 0 <= rank < len(found):
        raise NotFoundError(f"run {run.id} has no individual of rank {rank}")
    ranks = range(len(found)) if rank is None else range(rank, rank + 1)
    for r in ranks:
        if repeats_claim(config, g, genomes[r], found.fitness[r]):
            order = np.arange(len(found))
            return g, best_document(
                config, genomes, found.fitness, order, generation=g, run=run.id, rank=r
            )
        log.warning(
            "run %d generation %d rank %d: claimed fitness %r is not what the server's own "
            "evaluation gives; not served",
            run.id, g, r, float(found.fitness[r]),
        )  # fmt: skip
    which = (
        "no rank's claimed fitness is" if rank is None else f"rank {rank}'s claimed fitness is not"
    )
    raise UnconfirmedError(
        f"run {run.id} generation {g}: {which} what the server's own evaluation gives; "
        "nothing is served on a claim it does not repeat"
    )
