"""The job queue: the seam between the run loop and whoever evaluates (threads or zenoh workers).

A job is a contiguous slice of one generation (evorobotics.evolution.job_slices), cut when the
generation is asked: by the run's `job_size`, or by a `JobSizer` (the zenoh dispatcher's one
job per live worker, or one job for a generation that will be a span); a span's next
generation is always one job. The cut cannot change a result. Jobs, leases and
job results live in memory, one generation per run; the database holds only committed
generations. `lease` hands the next pending job of the running run served least recently to a
worker with a deadline; `complete` stores its result once (duplicates and late results are
acknowledged and dropped); `expire` and `release` return leases. When the last job of a
generation completes, the GA is told and asked at once and the next generation's jobs replace
it here; the generation is then written (see `server.manager`), either inside that
`complete` or, with `complete(..., defer=True)`, at a later `flush`: the dispatcher flushes
after it has sent the new jobs, so workers evaluate generation g + 1 while g is written.
Writes happen in the order generations were told, in one transaction per flush.

A span (`grant_span`) lets the worker holding a generation's only job evolve the next ones
itself: when that generation completes, the next one's job is leased to the same worker at
once (`complete(..., now=...)`), until the span is used up or the lease returns.

Why memory: a generation of the paper's population costs the server one transaction instead of
one per lease and per result. A crash loses leases and the results of the generation in flight,
never a committed generation; `ask` is a pure function of the committed GA state and the seed,
so a restarted server re-asks that generation and resumes bit-identically (results of a
generation asked before a crash but never written are dropped as late).
"""

from __future__ import annotations

import heapq
import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from evorobotics.evolution import job_slices
from evorobotics.ga import GAState
from schemas.run import RunConfig
from server.logs import context

log = logging.getLogger(__name__)

TOTALS = ("leased", "done", "requeued", "duplicates_dropped")
"""Keys of `JobQueue.totals()`."""


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


@dataclass(frozen=True)
class GenerationResults:
    """A fully evaluated generation, in the order it was asked."""

    run_id: int
    generation: int
    config: RunConfig
    genomes: np.ndarray
    """(population, n_weights) as asked."""
    fitness: np.ndarray
    """(population,)"""
    components: np.ndarray
    """(population, trials, 4)"""


class RunOverError(Exception):
    """A generation's write found its run no longer live (cancelled or failed meanwhile):
    nothing was written and nothing needs to be."""


@dataclass(frozen=True)
class Advance:
    """What the run manager makes of a fully evaluated generation."""

    following: np.ndarray | None
    """The next generation's genomes (asked from the told GA state), None when the run is over."""
    state: GAState | None
    """The told GA state (the next generation's `tell` starts from it)."""
    write: Callable[[Session], None]
    """Stores the generation inside the given transaction; raises RunOverError if the run is
    no longer live."""


GenerationDone = Callable[[GenerationResults], Advance]
"""Tells the GA a generation's fitness (in memory, no I/O): the next genomes and the write."""
RunFailed = Callable[[Session, int, str], None]
"""Fails a run (by id) inside the given transaction, after a job exhausted its attempts."""
JobSizer = Callable[[RunConfig, int], int]
"""Individuals per job for a run's generation (by number) about to be cut (see
`JobQueue.set_job_sizer`)."""


@dataclass
class _Slot:
    """Mutable state of one job of the generation in flight."""

    start: int
    stop: int
    status: str = "pending"
    """pending, leased or done."""
    worker: str | None = None
    deadline: float | None = None
    attempts: int = 0


@dataclass
class _Span:
    """A worker evolving generations itself: `left` more after the one in flight."""

    worker: str
    left: int


@dataclass
class _RunJobs:
    """The generation in flight of one run."""

    run_id: int
    generation: int
    config: RunConfig
    genomes: np.ndarray
    slots: list[_Slot]
    running: bool
    pending: list[int] = field(default_factory=list)
    """Heap of pending slot indices: the lowest index is leased first."""
    remaining: int = 0
    fitness: np.ndarray = field(default_factory=lambda: np.empty(0))
    components: np.ndarray = field(default_factory=lambda: np.empty(0))
    state: GAState | None = None
    span: _Span | None = None


@dataclass(frozen=True)
class _Unwritten:
    """A generation told and asked but not yet written."""

    results: GenerationResults
    write: Callable[[Session], None]
    last: bool
    """The run's last generation: writing it finishes the run."""


class JobQueue:
    """In-memory jobs of every live run; every call under one lock shared with the manager."""

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
        self._runs: dict[int, _RunJobs] = {}
        self._served: dict[int, int] = {}
        """run id -> lease sequence number of its last lease: fair sharing picks the smallest."""
        self._sequence = 0
        self._unwritten: list[_Unwritten] = []
        """Generations told and asked but not yet written, oldest first."""
        self._write_failures: dict[int, str] = {}
        """run id -> why its generation could not be written: the run is stopped (not leased)."""
        self._listeners: list[Callable[[], None]] = []
        self._totals = dict.fromkeys(TOTALS, 0)
        """Running totals since construction (see `totals`)."""
        self._job_size: JobSizer = lambda config, _generation: config.job_size

    def set_job_sizer(self, sizer: JobSizer) -> None:
        """How generations are cut from now on (default: the run's `job_size`).

        The zenoh dispatcher cuts a generation into one job per live worker (one job if it will
        be a span): every message and every `evaluate` call has a fixed cost, so fewer, larger
        jobs are cheaper. A span's next generation bypasses the sizer. Results cannot
        change (an individual's fitness does not depend on the slice it is evaluated in), and a
        generation keeps its cut while in flight, so within one server's life a job key names one
        slice (across a restart it may not: results carry their slice, see schemas.wire).
        """
        with self._lock:
            self._job_size = sizer

    def add_listener(self, listener: Callable[[], None]) -> Callable[[], None]:
        """Call `listener` (it must not block) whenever jobs may have become leasable (executors
        and the zenoh dispatcher wake on it); returns the function that removes it."""
        with self._lock:
            self._listeners.append(listener)

        def remove() -> None:
            with self._lock:
                if listener in self._listeners:
                    self._listeners.remove(listener)

        return remove

    def _announce(self) -> None:
        """Jobs may be leasable: wake the listeners (call without holding the lock where
        possible, so a listener never waits on it)."""
        with self._lock:
            listeners = list(self._listeners)
        for listener in listeners:
            listener()

    def add(
        self,
        *,
        run_id: int,
        config: RunConfig,
        generation: int,
        genomes: np.ndarray,
        running: bool,
        state: GAState | None = None,
        whole: bool = False,
    ) -> None:
        """Cut a committed run's generation into jobs (replacing any older generation), or
        into one job if `whole` (a span goes on whatever the sizer would say now).

        Call it after the transaction that made the generation askable has committed.
        """
        if genomes.ndim != 2 or genomes.shape[0] != config.population:
            raise ValueError(f"genomes of shape {genomes.shape} for population {config.population}")
        frozen = np.array(genomes, dtype=np.float64, order="C")
        frozen.flags.writeable = False
        with self._lock:
            size = config.population if whole else self._job_size(config, generation)
            slots = [_Slot(a, b) for a, b in job_slices(config.population, size)]
            self._runs[run_id] = _RunJobs(
                run_id=run_id,
                generation=generation,
                config=config,
                genomes=frozen,
                slots=slots,
                running=running,
                pending=list(range(len(slots))),
                remaining=len(slots),
                fitness=np.full(config.population, np.nan),
                components=np.full((config.population, config.trials, 4), np.nan),
                state=state,
            )
            self._served.setdefault(run_id, 0)
        if running:
            self._announce()

    def set_running(self, run_id: int, running: bool) -> None:
        """Pause (no new leases; leased jobs may still complete) or resume a run's jobs."""
        with self._lock:
            jobs = self._runs.get(run_id)
            if jobs is None:
                return
            jobs.running = running
            if not running:
                jobs.span = None
        if running:
            self._announce()

    def forget(self, run_id: int) -> None:
        """Drop a run's jobs (its results, if any arrive, are acknowledged and dropped)."""
        with self._lock:
            self._runs.pop(run_id, None)
            self._served.pop(run_id, None)

    def has_pending(self) -> bool:
        """Whether any running run has a job waiting for a worker."""
        with self._lock:
            return any(jobs.running and jobs.pending for jobs in self._runs.values())

    def lease(self, worker: str, now: float) -> Job | None:
        """The next pending job of the running run served least recently, or None."""
        with self._lock:
            chosen: _RunJobs | None = None
            for jobs in self._runs.values():
                if not (jobs.running and jobs.pending):
                    continue
                if chosen is None or (self._served[jobs.run_id], jobs.run_id) < (
                    self._served[chosen.run_id],
                    chosen.run_id,
                ):
                    chosen = jobs
            if chosen is None:
                return None
            index = heapq.heappop(chosen.pending)
            slot = chosen.slots[index]
            slot.status, slot.worker = "leased", worker
            slot.deadline = now + self._lease_seconds
            slot.attempts += 1
            self._sequence += 1
            self._served[chosen.run_id] = self._sequence
            self._totals["leased"] += 1
            return Job(
                key=JobKey(chosen.run_id, chosen.generation, index),
                config=chosen.config,
                start=slot.start,
                stop=slot.stop,
                genomes=chosen.genomes[slot.start : slot.stop],
                worker=worker,
                deadline=slot.deadline,
                attempt=slot.attempts,
            )

    def grant_span(self, key: JobKey, worker: str, generations: int) -> tuple[int, GAState | None]:
        """Let `worker`, holding job `key`, evolve up to `generations` generations from it.

        Only a generation cut into one job can be a span (its worker then has every fitness
        `tell` needs). Returns the generations granted (1: none beyond this job) and the GA
        state the job's `tell` starts from.
        """
        with self._lock:
            found = self._slot(key)
            if found is None:
                return 1, None
            jobs, slot = found
            if (
                not jobs.running
                or len(jobs.slots) != 1
                or slot.status != "leased"
                or slot.worker != worker
            ):
                return 1, None
            granted = max(1, min(generations, jobs.config.generations - jobs.generation))
            if granted == 1 or jobs.state is None:
                return 1, jobs.state
            jobs.span = _Span(worker, granted - 1)
            return granted, jobs.state

    def leased_to(self, key: JobKey) -> str | None:
        """The worker holding job `key` now, if it is leased."""
        with self._lock:
            found = self._slot(key)
            if found is None or found[1].status != "leased":
                return None
            return found[1].worker

    def genomes(self, key: JobKey) -> np.ndarray | None:
        """The genomes of job `key` while its generation is in flight."""
        with self._lock:
            found = self._slot(key)
            if found is None:
                return None
            return found[0].genomes[found[1].start : found[1].stop]

    def _slot(self, key: JobKey) -> tuple[_RunJobs, _Slot] | None:
        jobs = self._runs.get(key.run_id)
        if jobs is None or jobs.generation != key.generation:
            return None
        if not 0 <= key.index < len(jobs.slots):
            return None
        return jobs, jobs.slots[key.index]

    def complete(
        self, key: JobKey, result: JobResult, *, defer: bool = False, now: float | None = None
    ) -> bool:
        """Store a job's result; False when it was already stored or its run is over (dropped).

        The result of any lease (even an expired one) is accepted: evaluation is a pure
        function of the job, so every copy is the same. The last job tells the GA, installs the
        next generation's jobs and writes the generation (with any earlier unwritten ones, in
        order), now or (`defer`) at a later `flush`. If a write raises, the generations stay
        unwritten and the next flush retries them. With `now`, a span goes on: the next
        generation's job is leased to the span's worker from `now`.
        """
        with self._lock:
            found = self._slot(key)
            if found is None or found[1].status == "done":
                self._totals["duplicates_dropped"] += 1
                return False
            jobs, slot = found
            k, trials = slot.stop - slot.start, jobs.config.trials
            fitness = np.asarray(result.fitness, dtype=np.float64)
            components = np.asarray(result.components, dtype=np.float64)
            if fitness.shape != (k,) or components.shape != (k, trials, 4):
                raise ValueError(
                    f"result of job {key} has shapes {fitness.shape} and {components.shape}; "
                    f"expected ({k},) and ({k}, {trials}, 4)"
                )
            jobs.fitness[slot.start : slot.stop] = fitness
            jobs.components[slot.start : slot.stop] = components
            self._totals["done"] += 1
            if jobs.remaining == 1:
                self._advance(jobs, now)
                if not defer:
                    self.flush()
                return True
            if slot.status == "pending":  # a result of a lease already returned
                jobs.pending.remove(key.index)
                heapq.heapify(jobs.pending)
            jobs.remaining -= 1
            slot.status, slot.worker, slot.deadline = "done", None, None
            return True

    def _advance(self, jobs: _RunJobs, now: float | None) -> None:
        """Tell the GA, queue the generation's write and install the next generation's jobs
        (the next one of a span leased to its worker)."""
        results = GenerationResults(
            run_id=jobs.run_id,
            generation=jobs.generation,
            config=jobs.config,
            genomes=jobs.genomes,
            fitness=jobs.fitness,
            components=jobs.components,
        )
        advance = self._on_generation_done(results)
        self._unwritten.append(_Unwritten(results, advance.write, advance.following is None))
        if advance.following is None:
            self.forget(jobs.run_id)
        else:
            # A span granted goes on in one job even if the sizer would now cut slices (its
            # workers' speeds moved across the span threshold): cut otherwise, it would end,
            # and the generations its worker evaluated ahead would be dropped.
            span = jobs.span if jobs.span is not None and jobs.span.left > 0 else None
            self.add(
                run_id=jobs.run_id,
                config=jobs.config,
                generation=jobs.generation + 1,
                genomes=advance.following,
                running=jobs.running,
                state=advance.state,
                whole=span is not None and now is not None and jobs.running,
            )
            if span is not None and now is not None:
                self._go_on(self._runs[jobs.run_id], span, now)

    def _go_on(self, jobs: _RunJobs, span: _Span, now: float) -> None:
        """Lease the new generation's only job to the span's worker (as `lease` would)."""
        if not jobs.running or len(jobs.slots) != 1:
            return
        slot = jobs.slots[0]
        jobs.pending.clear()
        slot.status, slot.worker = "leased", span.worker
        slot.deadline = now + self._lease_seconds
        slot.attempts += 1
        jobs.span = _Span(span.worker, span.left - 1)
        self._sequence += 1
        self._served[jobs.run_id] = self._sequence
        self._totals["leased"] += 1

    def flush(self) -> None:
        """Write the told generations not yet written, oldest first, in one transaction.

        A generation whose run is over (RunOverError) is dropped; any other error leaves them
        unwritten and propagates: a later flush retries.
        """
        with self._lock:
            if not self._unwritten:
                return
            try:
                with self._sessions.begin() as session:
                    for item in self._unwritten:
                        item.write(session)
            except RunOverError:  # some run ended meanwhile: one transaction each instead
                self._flush_one_by_one()
            except Exception as exc:
                self._stall(exc)
                raise
            self._unwritten.clear()

    def _stall(self, exc: Exception) -> None:
        """The store refused a write: stop leasing for the runs it holds, so no run evolves on
        in memory; what is leased may still complete (at most one more generation each)."""
        message = f"database write failed: {type(exc).__name__}: {exc}"
        for item in self._unwritten:
            run_id = item.results.run_id
            if run_id not in self._write_failures:
                context(log, run=run_id).error(
                    "run %d stops leasing: generation %d not written: %s",
                    run_id,
                    item.results.generation,
                    message,
                )
            self._write_failures.setdefault(run_id, message[:500])
            jobs = self._runs.get(run_id)
            if jobs is not None:
                jobs.running = False

    def stalled(self) -> bool:
        """Whether a refused write stopped a run (the housekeeper retries it until it is in)."""
        with self._lock:
            return bool(self._write_failures)

    def write_failures(self) -> dict[int, str]:
        """Runs stopped by a refused write (run id -> why), once every generation is written;
        empty while a write is still outstanding."""
        with self._lock:
            return {} if self._unwritten else dict(self._write_failures)

    def clear_write_failures(self, run_ids: Iterable[int]) -> None:
        with self._lock:
            for run_id in run_ids:
                self._write_failures.pop(run_id, None)

    def _flush_one_by_one(self) -> None:
        while self._unwritten:
            item = self._unwritten[0]
            try:
                with self._sessions.begin() as session:
                    item.write(session)
            except RunOverError as exc:
                context(log, run=item.results.run_id).info(
                    "run %d generation %d not written: %s",
                    item.results.run_id,
                    item.results.generation,
                    exc,
                )
            self._unwritten.pop(0)

    def unwritten(self) -> int:
        """Generations told but not yet written (0 after a successful `flush`)."""
        with self._lock:
            return len(self._unwritten)

    def finishing(self) -> bool:
        """Whether an unwritten generation is its run's last (its write completes the run)."""
        with self._lock:
            return any(item.last for item in self._unwritten)

    def fail(self, key: JobKey, message: str) -> bool:
        """An evaluation raised: retry the job, or fail its run after `max_attempts` leases."""
        with self._lock:
            self.flush()
            found = self._slot(key)
            if found is None or found[1].status == "done":
                return False
            jobs, slot = found
            if slot.attempts >= self._max_attempts:
                with self._sessions.begin() as session:
                    self._on_run_failed(
                        session, key.run_id, f"job {key.generation}/{key.index} failed: {message}"
                    )
                self.forget(key.run_id)
                return True
            self._make_pending(jobs, key.index)
            self._totals["requeued"] += 1
        self._announce()
        return True

    def release(self, key: JobKey) -> bool:
        """A lease ended without a result (its worker left): the job is pending again at once."""
        with self._lock:
            found = self._slot(key)
            if found is None or found[1].status != "leased":
                return False
            self._make_pending(found[0], key.index)
            self._totals["requeued"] += 1
        self._announce()
        return True

    @staticmethod
    def _make_pending(jobs: _RunJobs, index: int) -> None:
        """The job waits for a lease again; a span it was part of is over."""
        jobs.span = None
        slot = jobs.slots[index]
        if slot.status != "pending":
            slot.status, slot.worker, slot.deadline = "pending", None, None
            heapq.heappush(jobs.pending, index)

    def expire(self, now: float) -> int:
        """Return every lease whose deadline has passed; the number returned."""
        count = 0
        with self._lock:
            for jobs in self._runs.values():
                for index, slot in enumerate(jobs.slots):
                    if (
                        slot.status == "leased"
                        and slot.deadline is not None
                        and slot.deadline < now
                    ):
                        self._make_pending(jobs, index)
                        count += 1
            self._totals["requeued"] += count
        if count:
            self._announce()
        return count

    def release_all(self) -> int:
        """Put every lease back (e.g. when evaluators are replaced); the number returned."""
        return self.expire(float("inf"))

    def totals(self) -> dict[str, int]:
        """Running totals since the queue was built: jobs `leased`, results accepted (`done`),
        leases returned to pending (`requeued`: expired, released, or retried after a failed
        evaluation) and results dropped because their job was already done or its generation
        or run is over (`duplicates_dropped`)."""
        with self._lock:
            return dict(self._totals)

    def counts(self) -> dict[str, int]:
        """Jobs of the generations in flight by status: pending, leased, done."""
        counts = {"pending": 0, "leased": 0, "done": 0}
        with self._lock:
            for jobs in self._runs.values():
                for slot in jobs.slots:
                    counts[slot.status] += 1
        return counts
