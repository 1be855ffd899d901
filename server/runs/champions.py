"""Champions of runs, and the store's reads of a run's best controller and archive.

A run completes with its validated champion (`evorobotics.evolution.champion`: the final
population's best on the run's validation set), stored in `controllers` and named by
`runs.champion_sha256` in the transaction that writes the last generation. Its validation
(seconds of simulation) runs in a thread of its own on the told generation, outside any
transaction: meanwhile the writer (`server.runs.writer`) goes on writing the other runs'
generations, so they never wait for it; the last generation joins the write after its champion
is known.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from evorobotics.document import ControllerDocument
from evorobotics.evolution import RunLoop, best_document, champion
from evorobotics.ga import rank
from evorobotics.strategies import Archive, traits
from schemas.run import RunConfig
from server.core.errors import NotFoundError, UnconfirmedError
from server.core.models import Run
from server.runs import crud
from server.runs.evaluation import repeats_claim
from server.runs.outbox import Written

log = logging.getLogger(__name__)

ARCHIVES_KEPT = 8
"""Replayed archives `Champions.archive` keeps (a dashboard polls the same run's)."""


class Champions:
    """Validates the champions of runs' last generations, one at a time, in a thread of its
    own; reads a run's best and archive from the store."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        lock: threading.RLock,
        told: threading.Event,
        fail: Callable[[Session, int, str], None],
    ) -> None:
        self._sessions = sessions
        self._lock = lock
        """The manager's: the validated and validating runs are under it."""
        self._told = told
        """Set once a champion is known, so the writer writes its generation without delay."""
        self._fail = fail
        """Fails a run (in the session) whose validation failed, saying why."""
        self._validator = ThreadPoolExecutor(1, thread_name_prefix="colony-champion")
        """Validates the champions of runs' last generations, one at a time."""
        self._validated: list[tuple[Written, ControllerDocument]] = []
        """Last generations whose champion is known, for the next write (under `_lock`)."""
        self._validating: set[int] = set()
        """Runs whose last generation is with the validator (under `_lock`)."""
        self._archives: dict[tuple[int, int], Archive] = {}
        """(run id, generations) -> its archive replayed (`archive`), oldest first."""

    def validate(self, item: Written) -> None:
        """Compute the champion of a run's last generation in the validator's thread; the
        writer writes that generation once it is known. A failure fails the run, saying why."""
        if item.run_id in self._validating:
            return
        self._validating.add(item.run_id)

        def validate() -> None:
            try:
                document = _champion(item)
            except Exception as exc:
                log.exception("run %d: champion validation failed", item.run_id)
                with self._lock, self._sessions.begin() as session:
                    self._validating.discard(item.run_id)
                    self._fail(session, item.run_id, f"champion validation failed: {exc}")
                return
            with self._lock:
                self._validating.discard(item.run_id)
                self._validated.append((item, document))
            self._told.set()

        self._validator.submit(validate)

    def take(self) -> list[tuple[Written, ControllerDocument]]:
        """The last generations whose champion is known, for the write at hand (under the
        manager's lock)."""
        validated, self._validated = self._validated, []
        return validated

    def keep(self, validated: list[tuple[Written, ControllerDocument]]) -> None:
        """Give back what `take` gave, for the next write (the store refused this one)."""
        self._validated += validated

    def wait(self) -> None:
        """Return once the validations submitted so far are done."""
        self._validator.submit(lambda: None).result()  # one thread: the ones before are done

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
    session: Session,
    run: Run,
    config: RunConfig,
    document: ControllerDocument | None = None,
) -> str | None:
    """Store a finished run's champion and name it on the run, so it is fetched and pushed
    by its sha256 after any restart; its sha256 (None without a committed generation).

    `document` is the champion computed from the told last generation; without it, it is
    computed from the stored one (the same document: ranks and genomes are stored bit for
    bit). It replaces a document of the same sha256 that a push stored before without
    the `validation` member."""
    last = config.generations - 1
    if document is None:
        latest = crud.latest_generation(session, run_id=run.id)
        if latest is None:
            return None
        last = latest.generation
        found, genomes = crud.ranked(session, run_id=run.id, generation=last)
        if traits(config).in_state:
            order = np.arange(len(found))
            document = champion(config, genomes, found.fitness, order, generation=last, run=run.id)
        else:  # its candidates may be an archive: the loop replayed from what it was told
            asked, fitness = np.empty_like(genomes), np.empty(len(found))
            asked[found.index], fitness[found.index] = genomes, found.fitness
            loop = RunLoop.resume(
                config, crud.history(session, run_id=run.id, generations=last + 1)
            )
            chosen, scores = loop.candidates(asked, fitness)
            document = champion(config, chosen, scores, rank(scores), generation=last, run=run.id)
    crud.put_controller(
        session,
        sha256=document.sha256,
        document=document.to_json(),
        run_id=run.id,
        generation=last,
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


def _champion(item: Written) -> ControllerDocument:
    """The champion of a run's last told generation, chosen among its candidates (seconds of
    simulation: no transaction)."""
    told = item.told
    genomes, fitness = item.candidates or (told.genomes, told.fitness)
    return champion(
        item.config, genomes, fitness, rank(fitness), generation=told.generation, run=item.run_id
    )
