"""The run manager: lifecycle of runs in the store.

Each live run is a `RunLoop` (evorobotics) served by the scheduler (`server.runs.scheduler`), which
tells and asks it as results come. The manager builds a run's loop from its last committed GA
state (`ask` is a pure function of that state and the seed, so a restarted server resumes
exactly), and its one thread writes what the scheduler told (`server.runs.writer`): every
`WRITE_AFTER_S` the told generations go into one transaction, so workers evaluate generation
g + 1 while g is written. A crash loses at most those, which a restart recomputes bit for bit.
Lifecycle changes use the ORM and write the told generations first.

Lifecycle: queued -> running <-> paused; queued/running/paused -> cancelled;
running -> completed | failed; failed -> queued (resumed from its last stored generation).
Terminal: completed, cancelled, and failed until resumed. A run completes with its validated
champion (`server.runs.champions`) in the transaction that writes its last generation.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Sequence

from sqlalchemy import Engine, func, select
from sqlalchemy.orm import Session

from evorobotics.document import ControllerDocument
from evorobotics.strategies import Archive
from schemas.api import TERMINAL
from schemas.run import RunConfig
from server.core.db import session_factory
from server.core.errors import NotFoundError, ServerError, TransitionError
from server.core.logs import context
from server.core.models import Run, Study, utcnow
from server.core.settings import Settings
from server.runs import crud
from server.runs.champions import Champions, store_champion
from server.runs.choosing import Choosing
from server.runs.policy import Policy
from server.runs.scheduler import Scheduler
from server.runs.writer import Writer

log = logging.getLogger(__name__)


WRITE_AFTER_S = 0.05
"""How long told generations wait to be written together (a transaction per generation cost
more than the rows in it), or at once when a run has `Policy.write_now` unwritten."""


class RunManager:
    """Owns the store's writes: runs, generations and individuals; feeds the scheduler."""

    def __init__(self, engine: Engine, settings: Settings) -> None:
        self.settings = settings
        self.sessions = session_factory(engine)
        self._lock = threading.RLock()
        """Held by lifecycle changes and writes (never by the scheduler's callers)."""
        self.scheduler = Scheduler(Policy.from_settings(settings))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._champions = Champions(self.sessions)
        """Reads a run's best and archive."""
        self._writer = Writer(
            self.sessions, settings, self.scheduler, self._champions, self._finish
        )
        """Writes the told generations (`flush`)."""

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
        return self._writer.refused()

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
                self.flush()
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
        """Write the told generations (`Writer.write`); then fail the runs whose jobs failed."""
        with self._lock:
            self._writer.write()
            failed = self.scheduler.take_failed()
            if failed:
                try:
                    with self.sessions.begin() as session:
                        for run_id, message in failed.items():
                            self._fail_id(session, run_id, message)
                except Exception:
                    self.scheduler.put_back_failed(failed)  # recorded on the next try
                    raise
                self.promote()

    def recover(self) -> None:
        """Serve again the generation in flight of every live run (its results died with the
        process; a run choosing its champion evaluates its last generation again); choose
        the champion of a completed run that has none (one completed before the store named
        champions) from its stored last generation."""
        with self._lock, self.sessions.begin() as session:
            unnamed = session.scalars(
                select(Run).where(Run.status == "completed", Run.champion_sha256.is_(None))
            )
            for run in unnamed:
                try:
                    with session.begin_nested():
                        self._serve(session, run)
                except (ServerError, ValueError) as exc:  # it stays completed, unnamed
                    context(log, run=run.id).warning(
                        "run %d: its champion cannot be chosen: %s", run.id, exc
                    )
            runs = session.scalars(select(Run).where(Run.status.in_(("running", "paused"))))
            for run in runs:
                try:
                    with session.begin_nested():
                        self._serve(session, run)
                except (ServerError, ValueError) as exc:  # a damaged row fails its run only
                    self._fail(session, run, f"cannot resume: {exc}")
        self.promote()

    def _serve(self, session: Session, run: Run) -> None:
        """Hand the run's loop, from its last committed generation, to the scheduler; after
        its last one (stored by an older server without its champion), its champion's
        stages, the last generation told again from the store."""
        config = RunConfig.model_validate_json(run.config)
        running = run.status in ("running", "completed")
        if run.generation < config.generations:
            loop = crud.replay(session, run=run, config=config, generation=run.generation)
            self.scheduler.add(run.id, loop, running=running)
            return
        loop, told = crud.retold(session, run=run, config=config)
        try:
            choosing = Choosing.new(run.id, loop, told, stored=True)
        except ValueError as exc:
            raise ServerError(f"run {run.id}: {exc}") from exc
        self.scheduler.choose(run.id, loop, choosing, running=running)

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
            self.flush()
            with self.sessions.begin() as session:
                run = crud.find_run(session, run_id=run_id)
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
            self.flush()
            with self.sessions.begin() as session:
                run = crud.find_run(session, run_id=run_id)
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
            self.flush()
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
            self.flush()
            with self.sessions.begin() as session:
                run = crud.find_run(session, run_id=run_id)
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
            self.flush()
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
            self.flush()
            with self.sessions.begin() as session:
                run = crud.find_run(session, run_id=run_id)
                if run.status not in allowed:
                    raise TransitionError(
                        f"run {run_id} is {run.status}; cannot change to {target} "
                        f"(allowed from {', '.join(sorted(allowed))})"
                    )
                run.status = target

    def _forget(self, run_id: int) -> None:
        """Drop a run's jobs and caches (it is over)."""
        self.scheduler.forget(run_id)
        self._writer.forget(run_id)

    # ends of runs ----------------------------------------------------------------------------

    def _finish(
        self, session: Session, run: Run, config: RunConfig, document: ControllerDocument
    ) -> None:
        """Complete the run with its champion `document` (a run completed by an older server
        without one: name it)."""
        if run.status != "completed":
            run.status, run.finished_at = "completed", utcnow()
            crud.settle_study(session, study_id=run.study_id)
        sha = store_champion(session, run, config, document)
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

    def archive(self, run_id: int) -> tuple[int, RunConfig, Archive]:
        """`Champions.archive`: the run's archive replayed from the store (cached)."""
        return self._champions.archive(run_id)

    def best(self, run_id: int) -> ControllerDocument:
        """`Champions.best`: the run's best controller, read from the store."""
        return self._champions.best(run_id)
