"""The job queue: the seam between the run loop and whoever evaluates (threads now, zenoh next).

A job is a fixed slice of one generation (evorobotics.evolution.job_slices) stored with its
genomes. `lease` hands the next pending job of the run served least recently to a worker with
a deadline; `complete` stores its result once (duplicates and late results are acknowledged
and dropped); `expire` returns lapsed leases. When the last job of a generation completes, the
generation is committed in the same transaction (see `server.manager`), so the database only
ever holds whole generations plus the job results that precede them.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from sqlalchemy import CursorResult, func, select, update
from sqlalchemy.orm import Session, sessionmaker

from evorobotics.evolution import job_slices
from schemas.run import RunConfig
from server.models import Job as JobRow
from server.models import Run, pack, unpack


@dataclass(frozen=True, order=True)
class JobKey:
    """Identifies a job (and its result) for ever: results are idempotent by this key."""

    run_id: int
    generation: int
    index: int


@dataclass(frozen=True)
class Job:
    """A leased job: everything an evaluator needs, nothing about who else is working."""

    key: JobKey
    config: RunConfig
    start: int
    stop: int
    genomes: np.ndarray
    """(stop - start, n_weights) float64, rows start..stop of the generation as asked."""
    worker: str
    deadline: float
    attempt: int


@dataclass(frozen=True)
class JobResult:
    """What evorobotics.evaluate.evaluate returned for a job's slice."""

    fitness: np.ndarray
    """(stop - start,)"""
    components: np.ndarray
    """(stop - start, trials, 4)"""


GenerationDone = Callable[[Session, Run, int], None]
"""Called inside the completing transaction when every job of (run, generation) is done."""
RunFailed = Callable[[Session, Run, str], None]
"""Called inside a transaction when a job exhausted its attempts."""


class JobQueue:
    """Jobs in the database; every write under one lock so SQLite never sees two writers."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        *,
        lock: threading.RLock,
        lease_seconds: float,
        max_attempts: int,
        on_generation_done: GenerationDone,
        on_run_failed: RunFailed,
    ) -> None:
        if lease_seconds <= 0:
            raise ValueError(f"lease_seconds must be > 0, got {lease_seconds}")
        if max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1, got {max_attempts}")
        self._sessions = sessions
        self._lock = lock
        self._lease_seconds = lease_seconds
        self._max_attempts = max_attempts
        self._on_generation_done = on_generation_done
        self._on_run_failed = on_run_failed
        self._configs: dict[int, RunConfig] = {}
        self._served: int | None = None
        self.work_available = threading.Event()
        """Set whenever jobs may have become leasable; executors wait on it."""

    def _config(self, run: Run) -> RunConfig:
        config = self._configs.get(run.id)
        if config is None:
            config = self._configs[run.id] = RunConfig.model_validate_json(run.config)
        return config

    def _next_served(self, session: Session) -> int:
        if self._served is None:
            self._served = int(session.scalar(select(func.coalesce(func.max(Run.served), 0))) or 0)
        self._served += 1
        return self._served

    def add(self, session: Session, *, run: Run, generation: int, genomes: np.ndarray) -> None:
        """Cut a generation's genomes into its fixed jobs (inside the caller's transaction)."""
        config = self._config(run)
        if genomes.shape[0] != config.population:
            raise ValueError(f"{genomes.shape[0]} genomes for population {config.population}")
        rows = []
        for index, (a, b) in enumerate(job_slices(config.population, config.job_size)):
            data, dtype, shape = pack(genomes[a:b])
            rows.append(
                JobRow(
                    run_id=run.id,
                    generation=generation,
                    index=index,
                    start=a,
                    stop=b,
                    status="pending",
                    attempts=0,
                    genomes=data,
                    dtype=dtype,
                    shape=shape,
                )
            )
        session.add_all(rows)
        self.work_available.set()

    def lease(self, worker: str, now: float) -> Job | None:
        """The next pending job of the running run served least recently, or None."""
        with self._lock, self._sessions.begin() as session:
            row = session.execute(
                select(JobRow, Run)
                .join(Run, Run.id == JobRow.run_id)
                .where(JobRow.status == "pending", Run.status == "running")
                .order_by(Run.served, Run.id, JobRow.generation, JobRow.index)
                .limit(1)
            ).first()
            if row is None:
                return None
            job, run = row
            job.status, job.worker = "leased", worker
            job.deadline = now + self._lease_seconds
            job.attempts += 1
            run.served = self._next_served(session)
            return Job(
                key=JobKey(job.run_id, job.generation, job.index),
                config=self._config(run),
                start=job.start,
                stop=job.stop,
                genomes=unpack(job.genomes, job.dtype, job.shape),
                worker=worker,
                deadline=job.deadline,
                attempt=job.attempts,
            )

    def complete(self, key: JobKey, result: JobResult) -> bool:
        """Store a job's result; False when it was already stored or its run is over (dropped).

        The result of any lease (even an expired one) is accepted: evaluation is a pure
        function of the job, so every copy is the same. The last job commits the generation.
        """
        with self._lock, self._sessions.begin() as session:
            job = session.get(JobRow, (key.run_id, key.generation, key.index))
            if job is None or job.status == "done":
                return False
            run = session.get(Run, key.run_id)
            if run is None or run.status in ("completed", "failed", "cancelled"):
                return False
            config = self._config(run)
            k = job.stop - job.start
            fitness = np.ascontiguousarray(result.fitness, dtype=np.float64)
            components = np.ascontiguousarray(result.components, dtype=np.float64)
            if fitness.shape != (k,) or components.shape != (k, config.trials, 4):
                raise ValueError(
                    f"result of job {key} has shapes {fitness.shape} and {components.shape}; "
                    f"expected ({k},) and ({k}, {config.trials}, 4)"
                )
            job.status, job.deadline, job.error = "done", None, None
            job.fitness, job.components = fitness.tobytes(), components.tobytes()
            run.evaluations += k
            session.flush()
            remaining = session.scalar(
                select(func.count())
                .select_from(JobRow)
                .where(
                    JobRow.run_id == key.run_id,
                    JobRow.generation == key.generation,
                    JobRow.status != "done",
                )
            )
            if remaining == 0:
                self._on_generation_done(session, run, key.generation)
            return True

    def fail(self, key: JobKey, message: str) -> bool:
        """An evaluation raised: retry the job, or fail its run after `max_attempts` leases."""
        with self._lock, self._sessions.begin() as session:
            job = session.get(JobRow, (key.run_id, key.generation, key.index))
            if job is None or job.status == "done":
                return False
            run = session.get(Run, key.run_id)
            if run is None:
                return False
            job.error = message
            if job.attempts >= self._max_attempts:
                self._on_run_failed(
                    session, run, f"job {key.generation}/{key.index} failed: {message}"
                )
            else:
                job.status, job.worker, job.deadline = "pending", None, None
                self.work_available.set()
            return True

    def expire(self, now: float) -> int:
        """Return every lease whose deadline has passed; the number returned."""
        with self._lock, self._sessions.begin() as session:
            result = session.execute(
                update(JobRow)
                .where(JobRow.status == "leased", JobRow.deadline < now)
                .values(status="pending", worker=None, deadline=None)
            )
            count = result.rowcount if isinstance(result, CursorResult) else 0
        if count:
            self.work_available.set()
        return int(count)

    def release_all(self) -> int:
        """At start: every lease belongs to a previous server life; put them back."""
        return self.expire(float("inf"))

    def results(
        self, session: Session, *, run_id: int, generation: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Genomes, fitness and components of a fully done generation, in slice order."""
        rows = list(
            session.scalars(
                select(JobRow)
                .where(JobRow.run_id == run_id, JobRow.generation == generation)
                .order_by(JobRow.index)
            )
        )
        genomes = np.concatenate([unpack(r.genomes, r.dtype, r.shape) for r in rows])
        fitness = np.concatenate([np.frombuffer(r.fitness or b"", np.float64) for r in rows])
        components = np.concatenate(
            [np.frombuffer(r.components or b"", np.float64) for r in rows]
        ).reshape(fitness.shape[0], -1, 4)
        return genomes, fitness, components

    def forget(self, run_id: int) -> None:
        self._configs.pop(run_id, None)
