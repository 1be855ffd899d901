"""The writer of told generations: what the scheduler told goes into the store, in one
transaction a write (`RunManager.flush`: every `WRITE_AFTER_S` and before a lifecycle change).

The write path uses SQLAlchemy Core statements (the manager's lifecycle changes use the ORM).
A generation is one row holding its statistics and what it was told (`server.runs.population`);
every `Settings.checkpoint_every`-th and the last also hold the GA state, genomes and
components, from which the generations after it are replayed. A run's last generation comes
with its champion (`server.runs.choosing`) and completes the run in the transaction that
writes it; a last generation an older server stored without its champion gets the champion
alone (`Written.stored`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import cast

import numpy as np
from sqlalchemy import Table, bindparam, insert, update
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from evorobotics.document import ControllerDocument
from evorobotics.strategies import traits
from schemas.run import RunConfig
from server.core.integrity import seal
from server.core.logs import context
from server.core.models import Generation, Run, utcnow
from server.core.settings import Settings
from server.runs import crud, population
from server.runs.champions import Champions
from server.runs.outbox import Written
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


class RunOverError(Exception):
    """A generation's write found its run no longer live (cancelled or failed meanwhile):
    nothing was written and nothing needs to be."""


LOG_EVERY_S = 1.0
"""A run's "generation written" lines go out at INFO at most this often (and for its first and
last generation), the others at DEBUG: a span writes hundreds of generations a second."""


class Writer:
    """Writes the generations the scheduler told, and stops the runs whose write the store
    refused until it takes it. Called under the manager's lock."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        settings: Settings,
        scheduler: Scheduler,
        champions: Champions,
        finish: Callable[[Session, Run, RunConfig, ControllerDocument], None],
    ) -> None:
        self._sessions = sessions
        self._settings = settings
        self._scheduler = scheduler
        self._finish = finish
        """Completes a run (in the session) after its last generation, with its champion."""
        self._write_failures: dict[int, str] = {}
        """run id -> why its generation could not be written: stopped until it is."""
        self._logged_at: dict[int, float] = {}
        """run id -> when a "generation written" line last went out at INFO (LOG_EVERY_S)."""
        self._tracker = (
            None
            if settings.tensorboard_dir is None
            else Tracker(settings.tensorboard_dir, champions.best)
        )
        """TensorBoard event files of the runs (COLONY_TENSORBOARD_DIR), if set."""

    def refused(self) -> dict[int, str]:
        """run id -> why the store refused its generation, until it is written and the run
        paused (`RunManager.write_refused`)."""
        return dict(self._write_failures)

    def forget(self, run_id: int) -> None:
        """Drop what is kept of a run (it is over)."""
        self._logged_at.pop(run_id, None)

    def write(self) -> None:
        """Write the told generations, oldest first, in one transaction (a run's last one with
        its champion). If the store refuses, the runs concerned stop leasing
        (what is leased may still complete) and the write is retried at the next call; once it
        is in, they are paused with the reason in `error`, so an operator sees it and
        resumes."""
        told = self._scheduler.take_told()
        try:
            self._write(told)
        except Exception as exc:
            self._scheduler.put_back(told)
            self._stall(told, exc)
            raise
        self._scheduler.written(told)
        if self._tracker is not None:
            self._tracker.written(told)
        self._settle_write_failures()

    def _write(self, told: list[Written]) -> None:
        if not told:
            return
        try:
            with self._sessions.begin() as session:
                self._write_generations(session, told)
        except RunOverError:  # some run ended meanwhile: one transaction each instead
            for item in told:
                try:
                    with self._sessions.begin() as session:
                        self._write_generations(session, [item])
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
            self._scheduler.set_running(item.run_id, False)

    def _settle_write_failures(self) -> None:
        if not self._write_failures:
            return
        with self._sessions.begin() as session:
            for run_id, message in self._write_failures.items():
                run = session.get(Run, run_id)
                if run is not None and run.status == "running":
                    run.status, run.error = "paused", message
                    context(log, run=run_id).warning(
                        "run %d paused after a refused write; resume it", run_id
                    )
        self._write_failures.clear()

    def _write_generations(self, session: Session, told: list[Written]) -> None:
        """Store each told generation g (statistics and what it was told; at a checkpoint also
        its GA state, genomes and components) and move its run to g + 1; complete a run after
        its last generation, with its champion (`Written.champion`). A run's consecutive
        generations move it in one UPDATE and all rows go in one INSERT: a statement costs
        SQLAlchemy more than the rows in it.

        A checkpoint is every `checkpoint_every`-th generation and the last: the others are
        rebuilt by replaying from the one before (`crud.replay`).
        """
        conn = session.connection()  # Core on the session's transaction: no ORM unit of work
        rows: list[dict[str, object]] = []
        finished: list[tuple[Written, ControllerDocument]] = []
        for segment in _segments(told):
            first, last = segment[0], segment[-1]
            if first.stored:
                self._name_champion(session, first)
                continue
            g, top = first.told.generation, _top(last)
            moved = conn.execute(
                _ADVANCE_RUN,
                {
                    "run": first.run_id,
                    "at": g,
                    "next": last.told.generation + 1,
                    "top": top if np.isfinite(top) else None,
                    "evaluated": first.config.population * len(segment),
                },
            )
            if moved.rowcount != 1:
                raise RunOverError(
                    f"run {first.run_id} is not live at generation {g}; nothing written"
                )
            rows.extend(self._row(item) for item in segment)
            if last.champion is not None:
                finished.append((last, last.champion))
        if rows:
            conn.execute(_INSERT_GENERATION, rows)
        for item, champion in finished:
            self._finish(session, crud.find_run(session, run_id=item.run_id), item.config, champion)

    def _row(self, item: Written) -> dict[str, object]:
        """The generation row of `item` (logged: its run's first and last, and one a second)."""
        run_id, told, config = item.run_id, item.told, item.config
        g, genomes, fitness, metrics = told.generation, told.genomes, told.fitness, told.metrics
        checkpoint = item.last or (g + 1) % self._settings.checkpoint_every == 0
        components = told.components
        if components is None:
            components = np.full((len(genomes), config.trials, 4), np.nan)
        frame = Stored(
            fitness=fitness,
            descriptors=None if traits(config).in_state else told.descriptors,
            genomes=genomes if checkpoint else None,
            components=components if checkpoint else None,
        )
        now = time.monotonic()
        loud = g == 0 or item.last
        if loud or now - self._logged_at.get(run_id, -math.inf) >= LOG_EVERY_S:
            self._logged_at[run_id] = now
            level = logging.INFO
        else:
            level = logging.DEBUG
        if log.isEnabledFor(level):
            context(log, run=run_id).log(
                level,
                "run %d generation %d written: best %.4g, mean %.4g",
                run_id,
                g,
                metrics.best,
                metrics.mean,
            )
        return {
            "run_id": run_id,
            "generation": g,
            "best": metrics.best,
            "mean": metrics.mean,
            "worst": metrics.worst,
            "nan_count": metrics.nan_count,
            "state": seal(population.encode_state(told.after)) if checkpoint else None,
            "population": seal(population.encode(frame)),
            "committed_at": utcnow(),
        }

    def _name_champion(self, session: Session, item: Written) -> None:
        """Complete with its champion a run whose last generation is stored already (a
        completed run without a champion: name it)."""
        run = session.get(Run, item.run_id)
        if (
            item.champion is None
            or run is None
            or run.generation != item.told.generation + 1
            or run.status not in ("running", "paused", "completed")
            or run.champion_sha256 is not None
        ):
            raise RunOverError(f"run {item.run_id} is not waiting for its champion")
        self._finish(session, run, item.config, item.champion)


def _top(item: Written) -> float:
    """The fitness of the generation's rank 0 (NaN if every evaluation failed)."""
    return float(item.told.fitness[item.told.metrics.order[0]])


def _segments(told: list[Written]) -> list[list[Written]]:
    """`told` cut into each run's stretches of consecutive generations, in order (a generation
    stored already, whose champion alone is written, is a stretch of its own)."""
    segments: list[list[Written]] = []
    open_: dict[int, list[Written]] = {}
    for item in told:
        segment = open_.get(item.run_id)
        if (
            segment is None
            or item.stored
            or segment[-1].stored
            or segment[-1].last
            or item.told.generation != segment[-1].told.generation + 1
        ):
            segment = open_[item.run_id] = []
            segments.append(segment)
        segment.append(item)
    return segments
