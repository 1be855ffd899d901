"""The run manager: lifecycle of runs in the store, and the writer of told generations.

Each live run is a `RunLoop` (evorobotics) served by the scheduler (`server.runs.scheduler`), which
tells and asks it as results come. The manager builds a run's loop from its last committed GA
state (`ask` is a pure function of that state and the seed, so a restarted server resumes
exactly), and its one thread writes what the scheduler told: every `WRITE_AFTER_S` the told
generations go into one transaction, so workers evaluate generation g + 1 while g is written.
A crash loses at most those, which a restart recomputes bit for bit.

The write path uses SQLAlchemy Core statements; lifecycle changes use the ORM and write the
told generations first. A generation is one row holding its statistics and what it was told
(`server.runs.population`); every `Settings.checkpoint_every`-th and the last also hold the GA state,
genomes and components, from which the generations after it are replayed.

Lifecycle: queued -> running <-> paused; queued/running/paused -> cancelled;
running -> completed | failed; failed -> queued (resumed from its last stored generation).
Terminal: completed, cancelled, and failed until resumed.

A run completes with its validated champion (`evorobotics.evolution.champion`: the final
population's best on the run's validation set), stored in `controllers` and named by
`runs.champion_sha256` in the transaction that writes the last generation. Its validation
(seconds of simulation) runs in a thread of its own on the told generation, outside any
transaction: meanwhile the writer goes on writing the other runs' generations, so they never
wait for it; the last generation joins the write after its champion is known.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import cast

import numpy as np
from sqlalchemy import Engine, Table, bindparam, func, insert, select, update
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session

from evorobotics.document import ControllerDocument
from evorobotics.evolution import RunLoop, best_document, champion
from evorobotics.ga import rank
from evorobotics.strategies import Archive, traits
from schemas.api import TERMINAL
from schemas.run import RunConfig
from server.core.db import session_factory
from server.core.errors import NotFoundError, ServerError, TransitionError
from server.core.integrity import seal
from server.core.logs import context
from server.core.models import Generation, Run, Study, utcnow
from server.core.settings import Settings
from server.runs import crud, population
from server.runs.outbox import Written
from server.runs.policy import Policy
from server.runs.population import Stored
from server.runs.scheduler import Scheduler
from server.runs.tracking import Tracker

log = logging.getLogger(__name__)

_RUNS = cast(Table, Run.__table__)
_GENERATIONS = cast(Table, Generation.__table__)
"""The tables behind the hot path's Core statements."""
_ADVANCE_RUN = (
    update(_RUNS)
    .where(
        _RUNS.c.id == bindparam("run"),
        _RUNS.c.generation == bindparam("at"),
        _RUNS.c.status.in_(("running", "paused")),
    )
    .values(
        generation=bindparam("next"),
        best_fitness=bindparam("top"),
        evaluations=_RUNS.c.evaluations + bindparam("evaluated"),
    )
)
"""Moves a live run from generation `at` to `next` (built once: building it cost more than
executing it)."""
_INSERT_GENERATION = insert(_GENERATIONS)


WRITE_AFTER_S = 0.05
"""How long told generations wait to be written together (a transaction per generation cost
more than the rows in it), or at once when a run has `Policy.write_now` unwritten."""


ARCHIVES_KEPT = 8
"""Replayed archives `RunManager.archive` keeps (a dashboard polls the same run's)."""


class RunOverError(Exception):
    """A generation's write found its run no longer live (cancelled or failed meanwhile):
    nothing was written and nothing needs to be."""


LOG_EVERY_S = 1.0
"""A run's "generation written" lines go out at INFO at most this often (and for its first and
last generation), the others at DEBUG: a span writes hundreds of generations a second."""


class RunManager:
    """Owns the store's writes: runs, generations and individuals; feeds the scheduler."""

    def __init__(self, engine: Engine, settings: Settings) -> None:
        self.settings = settings
        self.sessions = session_factory(engine)
        self._lock = threading.RLock()
        """Held by lifecycle changes and writes (never by the scheduler's callers)."""
        self.scheduler = Scheduler(Policy.from_settings(settings))
        self._write_failures: dict[int, str] = {}
        """run id -> why its generation could not be written: stopped until it is."""
        self._logged_at: dict[int, float] = {}
        """run id -> when a "generation written" line last went out at INFO (LOG_EVERY_S)."""
        """run id -> where the genome bytes of its last written generation are: saves a query
        per generation (see `_genome_at`)."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._validator = ThreadPoolExecutor(1, thread_name_prefix="colony-champion")
        """Validates the champions of runs' last generations, one at a time."""
        self._validated: list[tuple[Written, ControllerDocument]] = []
        """Last generations whose champion is known, for the next write (under `_lock`)."""
        self._validating: set[int] = set()
        """Runs whose last generation is with the validator (under `_lock`)."""
        self._archives: dict[tuple[int, int], Archive] = {}
        """(run id, generations) -> its archive replayed (`archive`), oldest first."""
        self._tracker = (
            None
            if settings.tensorboard_dir is None
            else Tracker(settings.tensorboard_dir, self.best)
        )
        """TensorBoard event files of the runs (COLONY_TENSORBOARD_DIR), if set."""

    # lifecycle of the manager -------------------------------------------------------------

    def start(self) -> None:
        """Resume the runs of a previous life, then write, expire and promote in a thread."""
        self.recover()
        self._stop.clear()
        self._thread = threading.Thread(target=self._work, name="colony-writer", daemon=True)
        self._thread.start()

    def alive(self) -> bool:
        """Whether the writer thread runs (`/healthz`)."""
        return self._thread is not None and self._thread.is_alive()

    def write_refused(self) -> dict[int, str]:
        """run id -> why the store refused its generation, for the runs stopped by a refused
        write that the store does not yet show paused (it refuses that update too, e.g. while
        the disk is full): the REST views and `/healthz` show them from here."""
        return dict(self._write_failures)

    def stop(self) -> None:
        """Stop the thread and write the generations told but not yet written (a restart
        would recompute them, bit for bit, but need not)."""
        self._stop.set()
        self.scheduler.close()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        try:
            self.flush()
        except Exception as exc:
            log.warning("generations told but not written at shutdown: %s", exc)

    def _work(self) -> None:
        """Every WRITE_AFTER_S write what was told; every housekeeping period expire leases
        and promote queued runs. Survives any error (logged), e.g. a database that is down."""
        housekept = time.monotonic()
        failing: str | None = None  # the last error, logged once with its traceback
        while not self._stop.is_set():
            self.scheduler.told_many.wait(WRITE_AFTER_S)
            self.scheduler.told_many.clear()
            try:
                self._flush()
                if time.monotonic() - housekept >= self.settings.housekeeping_seconds:
                    housekept = time.monotonic()
                    self.scheduler.expire()
                    self.promote()
            except Exception as exc:
                if str(exc) != failing:
                    log.exception("writer step failed; retrying")
                failing = str(exc)
            else:
                if failing is not None:
                    log.info("writer steps succeed again")
                failing = None

    def flush(self) -> None:
        """Write everything told, the last generations with their champions (this waits for
        their validation): what `stop` and callers outside the writer thread want."""
        self._flush()
        self._validator.submit(lambda: None).result()  # one thread: the ones before are done
        self._flush()

    def _flush(self) -> None:
        """Write the told generations, oldest first, in one transaction (a run's last one once
        its champion is validated); then fail the runs whose jobs failed. If the store refuses,
        the runs concerned stop leasing (what is leased may still complete) and the write is
        retried at the next call; once it is in, they are paused with the reason in `error`,
        so an operator sees it and resumes."""
        with self._lock:
            taken = self.scheduler.take_told()
            told = [item for item in taken if not item.last] + [i for i, _ in self._validated]
            champions = {item.run_id: document for item, document in self._validated}
            self._validated = []
            for item in taken:
                if item.last and item.run_id not in champions:
                    self._validate(item)
            try:
                self._write(told, champions)
            except Exception as exc:
                self._validated += [(i, champions[i.run_id]) for i in told if i.last]
                self.scheduler.put_back([i for i in told if not i.last])
                self._stall(told, exc)
                raise
            self.scheduler.written(told)
            if self._tracker is not None:
                self._tracker.written(told)
            self._settle_write_failures()
            failed = self.scheduler.take_failed()
            if failed:
                with self.sessions.begin() as session:
                    for run_id, message in failed.items():
                        self._fail_id(session, run_id, message)
                self.promote()

    def _validate(self, item: Written) -> None:
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
                with self._lock, self.sessions.begin() as session:
                    self._validating.discard(item.run_id)
                    self._fail_id(session, item.run_id, f"champion validation failed: {exc}")
                return
            with self._lock:
                self._validating.discard(item.run_id)
                self._validated.append((item, document))
            self.scheduler.told_many.set()

        self._validator.submit(validate)

    def _write(self, told: list[Written], champions: dict[int, ControllerDocument]) -> None:
        if not told:
            return
        try:
            with self.sessions.begin() as session:
                for item in told:
                    self._write_generation(session, item, champions.get(item.run_id))
        except RunOverError:  # some run ended meanwhile: one transaction each instead
            for item in told:
                try:
                    with self.sessions.begin() as session:
                        self._write_generation(session, item, champions.get(item.run_id))
                except RunOverError as exc:
                    context(log, run=item.run_id).info(
                        "run %d generation %d not written: %s",
                        item.run_id,
                        item.told.generation,
                        exc,
                    )

    def _stall(self, told: list[Written], exc: Exception) -> None:
        reason = exc.orig if isinstance(exc, DBAPIError) else exc  # not SQLAlchemy's SQL text
        message = f"database write failed: {type(reason).__name__}: {reason}".splitlines()[0]
        message = message[:500]
        for item in told:
            if item.run_id not in self._write_failures:
                context(log, run=item.run_id).error(
                    "run %d stops leasing: generation %d not written: %s",
                    item.run_id,
                    item.told.generation,
                    message,
                )
                self._write_failures[item.run_id] = message
            self.scheduler.set_running(item.run_id, False)

    def _settle_write_failures(self) -> None:
        if not self._write_failures:
            return
        with self.sessions.begin() as session:
            for run_id, message in self._write_failures.items():
                run = session.get(Run, run_id)
                if run is not None and run.status == "running":
                    run.status, run.error = "paused", message
                    context(log, run=run_id).warning(
                        "run %d paused after a refused write; resume it", run_id
                    )
        self._write_failures.clear()

    def recover(self) -> None:
        """Serve again the generation in flight of every live run (its results died with the
        process); store the champion of a completed run that has none (one completed before
        the store named champions)."""
        with self._lock, self.sessions.begin() as session:
            unnamed = session.scalars(
                select(Run).where(Run.status == "completed", Run.champion_sha256.is_(None))
            )
            for run in unnamed:
                sha = self.store_champion(session, run, RunConfig.model_validate_json(run.config))
                context(log, run=run.id).info("run %d: champion %s stored", run.id, sha)
            runs = session.scalars(select(Run).where(Run.status.in_(("running", "paused"))))
            for run in runs:
                config = RunConfig.model_validate_json(run.config)
                try:
                    with session.begin_nested():
                        if run.generation >= config.generations:
                            self._finish(session, run, config)
                        else:
                            self._serve(session, run)
                except ServerError as exc:  # a damaged row fails its run, not the server
                    self._fail(session, run, f"cannot resume: {exc}")
        self.promote()

    def _serve(self, session: Session, run: Run) -> None:
        """Hand the run's loop, from its last committed generation, to the scheduler."""
        config = RunConfig.model_validate_json(run.config)
        loop = crud.replay(session, run=run, config=config, generation=run.generation)
        self.scheduler.add(run.id, loop, running=run.status == "running")

    # run lifecycle ---------------------------------------------------------------------------

    def create_run(
        self,
        config: RunConfig,
        *,
        name: str | None = None,
        tags: Sequence[str] = (),
        study_id: int | None = None,
        condition: str | None = None,
    ) -> int:
        """Queue a run; it starts at once when fewer than `max_active_runs` are running."""
        with self._lock, self.sessions.begin() as session:
            run = self._add_run(
                session, config, name=name, tags=tags, study_id=study_id, condition=condition
            )
            run_id = run.id
        self._log_created(run_id, config)
        self.promote()
        return run_id

    def create_study(
        self, *, name: str, spec: str, runs: Sequence[tuple[RunConfig, str, str]]
    ) -> tuple[int, list[int]]:
        """Store a study and queue its runs ((config, run name, condition) each, tagged
        `study:NAME`) in one transaction, so a study exists whole or not at all; its id and
        its runs' ids. They queue with every other run (`promote`: oldest first)."""
        with self._lock, self.sessions.begin() as session:
            study = Study(name=name, spec=spec, status="running")
            session.add(study)
            session.flush()
            study_id = study.id
            added = [
                self._add_run(
                    session,
                    config,
                    name=run_name,
                    tags=[f"study:{name}"],
                    study_id=study_id,
                    condition=condition,
                )
                for config, run_name, condition in runs
            ]
            run_ids = [run.id for run in added]
        log.info("study %d %r created: %d runs", study_id, name, len(run_ids))
        for run_id, (config, _, _) in zip(run_ids, runs, strict=True):
            self._log_created(run_id, config)
        self.promote()
        return study_id, run_ids

    def _add_run(
        self,
        session: Session,
        config: RunConfig,
        *,
        name: str | None,
        tags: Sequence[str],
        study_id: int | None,
        condition: str | None,
    ) -> Run:
        run = Run(
            config=config.model_dump_json(),
            seed=config.seed,
            status="queued",
            generation=0,
            evaluations=0,
            name=name,
            tags=json.dumps(list(tags)),
            study_id=study_id,
            condition=condition,
        )
        session.add(run)
        session.flush()
        return run

    def _log_created(self, run_id: int, config: RunConfig) -> None:
        context(log, run=run_id).info(
            "run %d created: population %d, %d generations, seed %d",
            run_id,
            config.population,
            config.generations,
            config.seed,
        )

    def promote(self) -> None:
        """Start queued runs, oldest first, up to `max_active_runs` running at once."""
        with self._lock, self.sessions.begin() as session:
            running = session.scalar(
                select(func.count()).select_from(Run).where(Run.status == "running")
            )
            free = self.settings.max_active_runs - int(running or 0)
            if free <= 0:
                return
            queued = session.scalars(
                select(Run).where(Run.status == "queued").order_by(Run.id).limit(free)
            )
            for run in queued:
                try:
                    with session.begin_nested():
                        run.status = "running"
                        run.started_at = run.started_at or utcnow()
                        config = RunConfig.model_validate_json(run.config)
                        if run.generation >= config.generations:  # failed in validation
                            self._finish(session, run, config)
                            continue
                        self._serve(session, run)
                    context(log, run=run.id).info(
                        "run %d running from generation %d", run.id, run.generation
                    )
                except Exception as exc:  # a config the GA rejects fails its run, not the server
                    self._fail(session, run, f"cannot start: {exc}")

    def pause(self, run_id: int) -> None:
        with self._lock:
            self._transition(run_id, {"queued", "running"}, "paused")
            self.scheduler.set_running(run_id, False)
        context(log, run=run_id).info("run %d paused", run_id)

    def resume(self, run_id: int) -> None:
        """paused -> running; failed -> queued, to go on from its last stored generation. A
        run stopped by a refused write is written first (the store's error propagates while it
        still refuses), so it resumes from a stored generation."""
        with self._lock:
            self._flush()
            with self.sessions.begin() as session:
                run = self._get(session, run_id)
                if run.status not in ("paused", "failed"):
                    raise TransitionError(
                        f"run {run_id} is {run.status}; only a paused or failed run resumes"
                    )
                if run.status == "failed":
                    run.status, run.finished_at = "queued", None
                    crud.settle_study(session, study_id=run.study_id)
                else:
                    run.status = "running" if run.started_at is not None else "queued"
                run.error = None  # e.g. a refused write that paused it, or why it failed
                status = run.status
            self.scheduler.set_running(run_id, status == "running")
        context(log, run=run_id).info("run %d resumed (%s)", run_id, status)
        self.promote()

    def cancel(self, run_id: int) -> None:
        with self._lock:
            self._flush()
            with self.sessions.begin() as session:
                run = self._get(session, run_id)
                if run.status in TERMINAL:
                    raise TransitionError(f"run {run_id} is already {run.status}")
                run.status, run.finished_at = "cancelled", utcnow()
                crud.settle_study(session, study_id=run.study_id)
            self._forget(run_id)
        context(log, run=run_id).info("run %d cancelled", run_id)
        self.promote()

    def cancel_study(self, study_id: int) -> None:
        """Cancel the study's unfinished runs (one transaction); NotFoundError if none such."""
        with self._lock:
            self._flush()
            with self.sessions.begin() as session:
                if crud.get_study(session, study_id=study_id) is None:
                    raise NotFoundError(f"no study with id {study_id}")
                runs = crud.study_runs(session, study_id=study_id)
                live = [r for r in runs if r.status not in TERMINAL]
                now = utcnow()
                for run in live:
                    run.status, run.finished_at = "cancelled", now
                crud.settle_study(session, study_id=study_id)
            for run in live:
                self._forget(run.id)
        log.info("study %d cancelled: %d runs", study_id, len(live))
        self.promote()

    def delete_run(self, run_id: int) -> None:
        """Cancel the run if it is live, then delete it and its generations; its controllers
        stay (robots may run them), no longer naming it."""
        with self._lock:
            self._flush()
            with self.sessions.begin() as session:
                run = self._get(session, run_id)
                live = run.status not in TERMINAL
                study_id = run.study_id
                crud.delete_runs(session, run_ids=[run_id])
                crud.settle_study(session, study_id=study_id)
            self._forget(run_id)
        context(log, run=run_id).info("run %d deleted", run_id)
        if live:
            self.promote()

    def delete_study(self, study_id: int) -> None:
        """Cancel what still runs of the study, then delete it and its runs."""
        with self._lock:
            self._flush()
            with self.sessions.begin() as session:
                study = crud.get_study(session, study_id=study_id)
                if study is None:
                    raise NotFoundError(f"no study with id {study_id}")
                run_ids = [r.id for r in crud.study_runs(session, study_id=study_id)]
                crud.delete_runs(session, run_ids=run_ids)
                session.delete(study)
            for run_id in run_ids:
                self._forget(run_id)
        log.info("study %d deleted with its %d runs", study_id, len(run_ids))
        self.promote()

    def _transition(self, run_id: int, allowed: set[str], target: str) -> None:
        with self._lock:
            self._flush()
            with self.sessions.begin() as session:
                run = self._get(session, run_id)
                if run.status not in allowed:
                    raise TransitionError(
                        f"run {run_id} is {run.status}; cannot change to {target} "
                        f"(allowed from {', '.join(sorted(allowed))})"
                    )
                run.status = target

    def _get(self, session: Session, run_id: int) -> Run:
        run = crud.get_run(session, run_id=run_id)
        if run is None:
            raise NotFoundError(f"no run with id {run_id}")
        return run

    def _forget(self, run_id: int) -> None:
        """Drop a run's jobs and caches (it is over)."""
        self.scheduler.forget(run_id)
        self._logged_at.pop(run_id, None)

    # the store -------------------------------------------------------------------------------

    def _write_generation(
        self, session: Session, item: Written, document: ControllerDocument | None = None
    ) -> None:
        """Store generation g (statistics and what it was told; at a checkpoint also its GA
        state, genomes and components) and move the run to g + 1; complete the run after its
        last generation, with `document` (its champion) as the run's best.

        A checkpoint is every `checkpoint_every`-th generation and the last: the others are
        rebuilt by replaying from the one before (`crud.replay`).
        """
        run_id, told, config = item.run_id, item.told, item.config
        g, genomes, fitness, metrics = told.generation, told.genomes, told.fitness, told.metrics
        top = float(fitness[metrics.order[0]])
        conn = session.connection()  # Core on the session's transaction: no ORM unit of work
        moved = conn.execute(
            _ADVANCE_RUN,
            {
                "run": run_id,
                "at": g,
                "next": g + 1,
                "top": top if np.isfinite(top) else None,
                "evaluated": config.population,
            },
        )
        if moved.rowcount != 1:
            raise RunOverError(f"run {run_id} is not live at generation {g}; nothing written")
        checkpoint = item.last or (g + 1) % self.settings.checkpoint_every == 0
        components = told.components
        if components is None:
            components = np.full((len(genomes), config.trials, 4), np.nan)
        frame = Stored(
            fitness=fitness,
            descriptors=None if traits(config).in_state else told.descriptors,
            genomes=genomes if checkpoint else None,
            components=components if checkpoint else None,
        )
        conn.execute(
            _INSERT_GENERATION,
            {
                "run_id": run_id,
                "generation": g,
                "best": metrics.best,
                "mean": metrics.mean,
                "worst": metrics.worst,
                "nan_count": metrics.nan_count,
                "state": seal(population.encode_state(told.after)) if checkpoint else None,
                "population": seal(population.encode(frame)),
                "committed_at": utcnow(),
            },
        )
        now = time.monotonic()
        loud = g == 0 or item.last
        if loud or now - self._logged_at.get(run_id, -math.inf) >= LOG_EVERY_S:
            self._logged_at[run_id] = now
            level = logging.INFO
        else:
            level = logging.DEBUG
        context(log, run=run_id).log(
            level,
            "run %d generation %d written: best %.4g, mean %.4g",
            run_id,
            g,
            metrics.best,
            metrics.mean,
        )
        if item.last:
            self._finish(session, self._get(session, run_id), config, document)

    def _finish(
        self,
        session: Session,
        run: Run,
        config: RunConfig,
        document: ControllerDocument | None = None,
    ) -> None:
        run.status, run.finished_at = "completed", utcnow()
        sha = self.store_champion(session, run, config, document)
        crud.settle_study(session, study_id=run.study_id)
        self._forget(run.id)
        context(log, run=run.id).info("run %d completed; champion %s", run.id, sha)

    def _fail(self, session: Session, run: Run, message: str) -> None:
        run.status, run.error, run.finished_at = "failed", message, utcnow()
        crud.settle_study(session, study_id=run.study_id)
        self._forget(run.id)
        context(log, run=run.id).error("run %d failed: %s", run.id, message)

    def _fail_id(self, session: Session, run_id: int, message: str) -> None:
        run = session.get(Run, run_id)
        if run is not None and run.status not in TERMINAL:
            self._fail(session, run, message)

    # results -----------------------------------------------------------------------------------

    def store_champion(
        self,
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
                document = champion(
                    config, genomes, found.fitness, order, generation=last, run=run.id
                )
            else:  # its candidates may be an archive: the loop replayed from what it was told
                asked, fitness = np.empty_like(genomes), np.empty(len(found))
                asked[found.index], fitness[found.index] = genomes, found.fitness
                loop = RunLoop.resume(
                    config, crud.history(session, run_id=run.id, generations=last + 1)
                )
                chosen, scores = loop.candidates(asked, fitness)
                document = champion(
                    config, chosen, scores, rank(scores), generation=last, run=run.id
                )
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

    def _best(self, session: Session, run: Run, config: RunConfig) -> ControllerDocument | None:
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

    def archive(self, run_id: int) -> tuple[int, RunConfig, Archive]:
        """(generations, config, archive) of a map-elites, cma-me or novelty run after its
        committed generations, replayed from the store (about 1 s per 350 generations; the
        last ARCHIVES_KEPT are kept). NotFoundError for another strategy or before its first
        committed generation."""
        with self.sessions() as session:
            run = self._get(session, run_id)
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
        with self.sessions() as session:
            run = self._get(session, run_id)
            stored = crud.champion(session, run=run)
            if stored is not None:
                return ControllerDocument.from_json(stored.document)
            document = self._best(session, run, RunConfig.model_validate_json(run.config))
        if document is None:
            raise NotFoundError(f"run {run_id} has no completed generation yet")
        return document


def _champion(item: Written) -> ControllerDocument:
    """The champion of a run's last told generation, chosen among its candidates (seconds of
    simulation: no transaction)."""
    told = item.told
    genomes, fitness = item.candidates or (told.genomes, told.fitness)
    return champion(
        item.config, genomes, fitness, rank(fitness), generation=told.generation, run=item.run_id
    )
