"""The scheduler: every decision of the job path, as a state machine without I/O.

It owns the generations in flight (one `RunLoop` per live run, its generation cut into jobs),
the one lease table on one injectable clock, spans, the worker table and the generations told
but not yet written. Inputs are calls (a worker asks, a result arrives, a worker leaves, the
clock passes a deadline); outputs are jobs, acknowledgements, told generations to store and
runs to fail. It knows nothing of zenoh, HTTP or the database; the zenoh dispatcher, the
in-process executor and the run manager drive it, each call under one lock held briefly.

A job is a contiguous slice of a generation. Only its lease holder's result counts: a late or
duplicate result is acknowledged as dropped. The result of the last job tells the run loop,
which asks the next generation at once. A span lets the worker holding a generation's only
job evolve the following ones itself (ask and tell are pure functions of the GA state and the
seed): each accepted generation moves the lease on to the next, and the worker proves with a
digest that it evaluated the genomes asked here.

Spot-checks: runs are deterministic, so the scheduler re-evaluates `Policy.spot_checks`
individuals of every result of a listed worker, chosen with `secrets` (never the run's seed
stream), and compares them bit for bit. A mismatch quarantines the worker's credential for the
life of the process: every worker named USER or USER.* (the names zenoh's roles let one
credential use) gets no more jobs and its results in the generations in flight return to
pending, so honest workers evaluate them (docs/reliability.md, "Spot-checks").

Errors: a worker's error result says nothing about the run, only about that worker. Its job
returns to pending for other credentials; once `Policy.max_attempts` credentials erred on it, or
none other is live to take it, the server evaluates it itself (the referee's thread). Only the
server's own evaluation failing (the referee's, or an in-process executor's) fails a run. A
credential whose results err `Policy.errors_quarantine` times in a row is quarantined.
"""

from __future__ import annotations

import heapq
import logging
import math
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from evorobotics.evaluate import evaluate, implausible, robot_steps
from evorobotics.evolution import RunLoop, Told, job_slices
from evorobotics.strategies import traits
from schemas.run import RunConfig
from schemas.wire import Ack, Job, JobKey, Result, WorkerStatus, genome_digest
from server.core.logs import context
from server.core.settings import Settings

log = logging.getLogger(__name__)

SPEED_MIN = 1.0
SPEED_MAX = 1e9
"""Robot-steps/s a worker may claim: clamped into this range, so no report gives a lease
beyond `lease_max_s` or a span beyond the run (numba reaches about 1e7 on one core)."""
TOTALS = ("leased", "done", "requeued", "duplicates_dropped")
"""Keys of `Scheduler.totals()`."""
SPOT_TOTALS = ("results_checked", "individuals_checked", "robot_steps_checked", "mismatches")
"""Keys of `Scheduler.spot_totals()`."""
REFEREE = "(server)"
"""The lease holder while the server evaluates a job itself (not a valid worker name)."""
_CHOOSE = secrets.SystemRandom()
"""Picks the individuals to re-evaluate: a worker cannot predict them from the run's seed."""


@dataclass(frozen=True)
class Policy:
    """Lease, span and retry policy; the defaults serve a lab network."""

    lease_min_s: float = 10.0
    lease_max_s: float = 300.0
    lease_factor: float = 10.0
    """lease = lease_factor x the job's robot-steps / the worker's speed as the scheduler
    measured it (never as the worker claims it), clamped to the range."""
    lease_unknown_s: float = 120.0
    """Lease for a worker with no measured speed yet (its first job compiles the kernels)."""
    jobs_per_worker: int = 1
    """A generation is cut into this many jobs per live worker."""
    span_below_s: float = 0.02
    """A generation a worker evaluates faster than this runs in spans (0: never) while runs are
    fewer than workers: below it the round trip per generation costs more than parallel slices
    save (on 2 cores, slices won from about 20 ms a generation: bench/dispatch.py --sweep).
    With at least as many runs as workers (a study), every worker can evolve a run of its own:
    whole generations in spans then whatever a generation's length (bench/study.py)."""
    span_s: float = 5.0
    """A span covers about this much evaluation time, then its worker asks again."""
    max_attempts: int = 3
    """Credentials whose evaluation of a job may err before the server evaluates it itself
    (whose error alone fails the run)."""
    errors_quarantine: int = 3
    """Error results in a row, with none accepted between, that quarantine a credential."""
    gone_keep_s: float = 600.0
    """How long a departed worker stays listed as gone."""
    store_lag_s: float = 0.25
    """How long a told generation may wait for the store: past this its run leases nothing and
    a span ends with its current message, so a store that blocks or refuses writes (or a
    writer that stopped) stops its runs within that much evolution and one span message. The
    writer takes told generations every 0.05 s and writes them in milliseconds."""
    write_now: int = 4
    """Told generations of one run that make the store write at once (`told_many`)."""
    spot_checks: int = 0
    """Individuals of each result of a listed worker re-evaluated here (0: none). The server
    sets it from COLONY_SPOT_CHECKS (default 1); a bare scheduler trusts every result, so tests
    and benches may stand a fake evaluator in for the science."""

    def __post_init__(self) -> None:
        for name in ("lease_min_s", "lease_factor", "lease_unknown_s", "span_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.lease_max_s >= self.lease_min_s:
            raise ValueError(f"lease_max_s must be >= lease_min_s, got {self.lease_max_s}")
        if self.span_below_s < 0 or self.gone_keep_s < 0 or self.spot_checks < 0:
            raise ValueError("span_below_s, gone_keep_s and spot_checks must be >= 0")
        if min(self.jobs_per_worker, self.max_attempts, self.errors_quarantine, self.write_now) < 1:
            raise ValueError(
                "jobs_per_worker, max_attempts, errors_quarantine and write_now must be >= 1"
            )
        if not self.store_lag_s > 0:
            raise ValueError(f"store_lag_s must be > 0, got {self.store_lag_s}")

    @classmethod
    def from_settings(cls, settings: Settings) -> Policy:
        """The server's policy from its settings (COLONY_LEASE_*, ...). ValueError if
        inconsistent."""
        return cls(
            lease_min_s=settings.lease_min_seconds,
            lease_max_s=settings.lease_max_seconds,
            lease_unknown_s=settings.lease_unknown_seconds,
            jobs_per_worker=settings.jobs_per_worker,
            span_below_s=settings.span_below_seconds,
            span_s=settings.span_seconds,
            max_attempts=settings.max_attempts,
            errors_quarantine=settings.errors_quarantine,
            spot_checks=settings.spot_checks,
        )

    def lease_seconds(self, robot_steps: int, speed: float | None) -> float:
        """The lease of a job of `robot_steps` for a worker measured at `speed` robot-steps/s
        (None: not measured yet)."""
        if speed is None:
            return self.lease_unknown_s
        wanted = self.lease_factor * robot_steps / clamp_speed(speed)
        return min(max(self.lease_min_s, wanted), self.lease_max_s)

    def span_generations(self, config: RunConfig, speed: float | None, *, crowded: bool) -> int:
        """Generations of `config` a worker of `speed` evolves in one span (1: no span);
        `crowded`: runs are at least as many as workers (no slices needed to keep all busy)."""
        if speed is None or self.span_below_s == 0:
            return 1
        seconds = robot_steps(config, config.population) / clamp_speed(speed)
        if seconds >= self.span_below_s and not crowded:
            return 1
        return max(1, int(self.span_s / seconds))


def run_job(job: Job, worker: str) -> Result:
    """Evaluate `job` (one generation of its slice) as a Result; an error, or an evaluation
    no Result can carry (non-finite fitness, descriptors outside [0, 1]), becomes one."""
    began = time.perf_counter()
    try:
        evaluation = evaluate(job.config, job.key.generation, job.genomes)
        if not np.isfinite(evaluation.fitness).all():  # a Result refuses it: a ValueError here
            raise ValueError("evaluation returned non-finite fitness")
        seconds = time.perf_counter() - began
        return Result(
            key=job.key,
            worker=worker,
            start=job.start,
            stop=job.stop,
            robot_steps_per_s=(
                robot_steps(job.config, job.stop - job.start) / seconds if seconds > 0 else 0.0
            ),
            seconds=seconds,
            fitness=evaluation.fitness[None],
            components=evaluation.components[None],
            descriptors=evaluation.descriptors[None],
        )
    except Exception as exc:  # an evaluation error is the run's problem, not the thread's
        return Result(
            key=job.key,
            worker=worker,
            start=job.start,
            stop=job.stop,
            error=f"{type(exc).__name__}: {exc}",
        )


def credential(worker: str) -> str:
    """The zenoh user a worker's name belongs to: `USER` of `USER` or `USER.anything`
    (schemas.security.ZenohRoles; worker users contain no '.')."""
    return worker.partition(".")[0]


def clamp_speed(speed: float) -> float:
    """A reported speed within [SPEED_MIN, SPEED_MAX] (NaN counts as the minimum)."""
    return min(max(speed, SPEED_MIN), SPEED_MAX) if speed == speed else SPEED_MIN


@dataclass(frozen=True)
class Written:
    """A told generation waiting to be stored."""

    run_id: int
    config: RunConfig
    told: Told
    last: bool = False
    """The run's last generation: storing it completes the run."""
    candidates: tuple[np.ndarray, np.ndarray] | None = None
    """With `last`: the genomes and fitness the champion is chosen from (`RunLoop.candidates`:
    the final generation, or a quality-diversity run's archive)."""


@dataclass
class _Slot:
    start: int
    stop: int
    status: str = "pending"
    """pending, leased or done."""
    erred: dict[str, tuple[str, str]] = field(default_factory=dict)
    """Credential -> (worker, error) of each whose evaluation of it erred: it is never leased
    to them again, and once it is done (so the job was fine) each error counts against them."""
    worker: str | None = None
    """Whose result filled it (done): discarded if that worker fails a spot-check."""


@dataclass
class _Run:
    run_id: int
    loop: RunLoop
    running: bool
    slots: list[_Slot]
    pending: list[int]
    """Heap of pending slot indices: the lowest is leased first."""
    fitness: np.ndarray
    components: np.ndarray
    descriptors: np.ndarray
    remaining: int
    served: int = 0
    """Sequence number of its last lease: the run served least recently goes first."""
    erred: bool = False
    """Some slot of this generation erred: leases skip the slots a credential erred on."""


@dataclass
class _Lease:
    key: JobKey
    worker: str
    deadline: float
    start: int
    stop: int
    leased_at: float = 0.0
    """When it was leased, on the scheduler's clock: its result measures the worker's speed."""
    span_left: int = 0
    """Generations of a span after this one."""
    asked_by_worker: bool = False
    """A span's generation the worker asked itself: its result must carry the digest."""


@dataclass
class _Worker:
    name: str
    host: str = ""
    speed: float | None = None
    """Robot-steps/s as it claims (clamped): spans and job sizes, which it can only waste."""
    measured: float | None = None
    """Robot-steps/s of its last accepted job, lease to result on the scheduler's clock: its
    leases, which a slow claim must not stretch."""
    jobs_done: int = 0
    evaluations: int = 0
    late: int = 0
    last_seen: float = 0.0
    """Unix time (for display only)."""
    asked_at: float | None = None
    """When it last asked for a job, on the scheduler's clock: only a name that asks counts
    as a worker (a credential can declare tokens for any number of names)."""
    gone_at: float | None = None
    serving: bool = True
    """False while it speaks another protocol: it is answered idle, never counted."""
    spans: bool = True
    """False for in-process evaluators, and once it evaluated genomes other than asked."""
    listed: bool = True
    """False for in-process evaluators: not shown as workers, never spot-checked (they run
    this process's own code)."""
    quarantine: str | None = None
    """Why it failed a spot-check: no more jobs, its results dropped, kept listed for good."""


class Scheduler:
    """Jobs, leases, spans and workers of every live run; thread-safe, one lock per call."""

    def __init__(
        self,
        policy: Policy | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.policy = policy or Policy()
        self._clock = clock
        self._wall = wall
        self._lock = threading.Lock()
        self._runs: dict[int, _Run] = {}
        self._leases: dict[JobKey, _Lease] = {}
        self._workers: dict[str, _Worker] = {}
        self._banned: dict[str, str] = {}
        """Quarantined credentials (`credential(name)`) and why: a new name under one is too."""
        self._errors: dict[str, int] = {}
        """Credential -> its error results since its last accepted one."""
        self._referee = ThreadPoolExecutor(1, thread_name_prefix="colony-referee")
        """Evaluates the jobs no worker could (`REFEREE` holds their leases meanwhile)."""
        self._told: list[Written] = []
        self._unwritten: dict[int, deque[float]] = {}
        """run id -> when each generation told and not yet written was told, oldest first."""
        self.told_many = threading.Event()
        """Set when a run has `write_now` generations unwritten: the store should write now."""
        self._failed: dict[int, str] = {}
        self._sequence = 0
        self._totals = dict.fromkeys(TOTALS, 0)
        self._spot = dict.fromkeys(SPOT_TOTALS, 0)
        self._listeners: list[Callable[[], None]] = []

    def now(self) -> float:
        """The scheduler's clock (leases and deadlines are on it)."""
        return self._clock()

    def close(self) -> None:
        """Finish the server's own evaluation in hand; no more after."""
        self._referee.shutdown(wait=True, cancel_futures=True)

    # runs ------------------------------------------------------------------------------------

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call `listener` (it must not block) whenever jobs may have become leasable."""
        with self._lock:
            self._listeners.append(listener)

    def remove_listener(self, listener: Callable[[], None]) -> None:
        with self._lock:
            if listener in self._listeners:
                self._listeners.remove(listener)

    def add(self, run_id: int, loop: RunLoop, *, running: bool) -> None:
        """Serve `loop`'s current generation (replacing anything of the run in flight)."""
        with self._lock:
            self._drop_leases(run_id)
            self._install(run_id, loop, running, served=self._sequence)
        self._announce()

    def set_running(self, run_id: int, running: bool) -> None:
        """Pause (no new leases; leased jobs may still complete) or resume a run."""
        with self._lock:
            run = self._runs.get(run_id)
            if run is not None:
                run.running = running
        self._announce()

    def forget(self, run_id: int) -> None:
        """Drop a run (over): its results, if any arrive, are acknowledged as dropped."""
        with self._lock:
            self._drop_run(run_id)

    def take_told(self) -> list[Written]:
        """The generations told since the last call, oldest first, for the store."""
        with self._lock:
            told, self._told = self._told, []
            return told

    def written(self, told: list[Written]) -> None:
        """The store has `told` (or dropped it, its run being over): their runs may go on."""
        with self._lock:
            for item in told:
                times = self._unwritten.get(item.run_id)
                if times:
                    times.popleft()
                if not times:
                    self._unwritten.pop(item.run_id, None)
        self._announce()

    def put_back(self, told: list[Written]) -> None:
        """Told generations the store refused: first in line for the next `take_told`."""
        with self._lock:
            self._told[:0] = told

    def take_failed(self) -> dict[int, str]:
        """Runs (id -> why) whose job failed in the server's own evaluation since the last
        call: the store fails them (after writing their told generations)."""
        with self._lock:
            failed, self._failed = self._failed, {}
            return failed

    def has_pending(self) -> bool:
        with self._lock:
            return any(self._leasable(run) for run in self._runs.values())

    # workers ---------------------------------------------------------------------------------

    def join(
        self,
        worker: str,
        *,
        host: str | None = None,
        speed: float | None = None,
        serving: bool = True,
        spans: bool = True,
        listed: bool = True,
        asked: bool = True,
    ) -> None:
        """`worker` is alive (a request, or only a token: `asked` False): noted with what it
        says of itself. An unlisted one (an in-process evaluator) leases like any other but is
        not in `workers`."""
        with self._lock:
            record = self._touch(worker)
            if asked:
                record.asked_at = self._clock()
            record.serving = serving
            record.spans = record.spans and spans
            record.listed = record.listed and listed
            if host:
                record.host = host[:255]
            if speed is not None:
                record.speed = clamp_speed(speed)

    def leave(self, worker: str) -> list[JobKey]:
        """`worker` is gone (its token vanished): its leases return at once; their keys."""
        with self._lock:
            record = self._workers.setdefault(worker, _Worker(worker))
            record.gone_at = self._clock()
            released = self._release_where(lambda lease: lease.worker == worker)
        self._announce()
        return released

    def workers(self) -> list[WorkerStatus]:
        """Every known worker, gone ones too until `gone_keep_s` after they left (quarantined
        ones for good)."""
        with self._lock:
            busy = {lease.worker for lease in self._leases.values()}
            return [
                WorkerStatus(
                    name=w.name,
                    host=w.host,
                    state="gone" if w.gone_at is not None else "busy" if w.name in busy else "idle",
                    jobs_done=w.jobs_done,
                    evaluations=w.evaluations,
                    late=w.late,
                    robot_steps_per_s=w.speed,
                    last_seen=w.last_seen,
                )
                for w in sorted(self._workers.values(), key=lambda w: w.name)
                if w.listed
            ]

    def quarantined(self) -> dict[str, str]:
        """Workers that failed a spot-check: name -> why (worker, run, generation, individual,
        claimed and recomputed fitness)."""
        with self._lock:
            return {w.name: w.quarantine for w in self._workers.values() if w.quarantine}

    # jobs ------------------------------------------------------------------------------------

    def lease(self, worker: str) -> Job | None:
        """The next job for `worker`, leased to it, or None. A worker asks only with empty
        hands, so any lease it still holds lost its reply: that job returns first."""
        with self._lock:
            record = self._touch(worker)
            record.asked_at = self._clock()
            self._release_where(lambda lease: lease.worker == worker)
            if record.quarantine is not None:
                return None
            self._referee_stranded()
            excluded = credential(worker) if record.listed else None
            chosen: _Run | None = None
            index = 0
            for run in self._runs.values():
                if not self._leasable(run) or (
                    chosen is not None
                    and (run.served, run.run_id) >= (chosen.served, chosen.run_id)
                ):
                    continue
                pick = self._pick(run, excluded)
                if pick is not None:
                    chosen, index = run, pick
            if chosen is None:
                return None
            self._unpend(chosen, index)
            slot = chosen.slots[index]
            loop = chosen.loop
            key = JobKey(run_id=chosen.run_id, generation=loop.generation, index=index)
            config = loop.config
            span = 1
            if record.spans and len(chosen.slots) == 1 and traits(config).in_state:
                wanted = self.policy.span_generations(config, record.speed, crowded=self._crowded())
                span = max(1, min(wanted, config.generations - loop.generation))
            lease_s = self._lease(chosen, index, worker, span_left=span - 1)
            return Job(
                key=key,
                start=slot.start,
                stop=slot.stop,
                config=config,
                genomes=loop.ask()[slot.start : slot.stop],
                span=span,
                state=loop.state.to_arrays() if span > 1 else None,
                lease_s=lease_s,
            )

    def settle(self, result: Result) -> Ack:
        """Take a result: each of its generations in order while the worker holds the lease
        (a span's lease then moves on); an error is retried or fails the run."""
        with self._lock:
            ack = self._settle(result)
        self._announce()
        return ack

    def _settle(self, result: Result) -> Ack:
        record = self._touch(result.worker, revive=False)
        if record.quarantine is not None:
            return Ack(key=result.key, accepted=False, reason="worker quarantined")
        if result.robot_steps_per_s > 0:
            record.speed = clamp_speed(result.robot_steps_per_s)
        mismatch = self._spot_check(result, record)
        if mismatch is not None:
            self._spot["mismatches"] += 1
            self._quarantine(record.name, mismatch)
            return Ack(key=result.key, accepted=False, reason="spot-check failed: quarantined")
        ack = Ack(key=result.key, accepted=False, reason="no lease held: late or duplicate")
        following = result.key
        for i in range(result.generations):
            key = result.key.at(result.key.generation + i)
            lease = self._leases.get(key)
            if (
                lease is None
                or lease.worker != result.worker
                or (
                    result.start is not None
                    and (result.start, result.stop) != (lease.start, lease.stop)
                )
            ):
                self._totals["duplicates_dropped"] += result.generations - i
                if result.fitness is not None:
                    record.late += (result.generations - i) * result.fitness.shape[1]
                break
            del self._leases[key]
            if result.error is not None:
                self._erred(key, record, result.error)
                ack = Ack(key=result.key, accepted=True, reason="error recorded")
                break
            wrong = self._digest_error(result, i, lease, record)
            if wrong is not None:
                context(log, worker=result.worker).warning(
                    "worker %s: %s; no more spans for it", result.worker, wrong
                )
                self._make_pending(self._runs[key.run_id], key.index)  # asked here next time
                ack = Ack(key=result.key, accepted=True, reason="error recorded")
                break
            fitness, components, descriptors = result.fitness, result.components, result.descriptors
            if fitness is None or components is None or descriptors is None:  # handled above
                break
            run = self._runs.get(key.run_id)
            forged = (
                None if run is None else implausible(run.loop.config, fitness[i], components[i])
            )
            if run is not None and forged is not None:
                self._make_pending(run, key.index)
                self._spot["mismatches"] += 1
                self._quarantine(
                    record.name, f"worker {result.worker} run {key.run_id} generation "
                    f"{key.generation}: {forged}"
                )  # fmt: skip
                return Ack(key=result.key, accepted=False, reason=f"refused: {forged}")
            if run is not None:  # before a span's lease moves on at this speed
                took = max(self._clock() - lease.leased_at, 1e-6)
                steps = robot_steps(run.loop.config, lease.stop - lease.start)
                record.measured = clamp_speed(steps / took)
            self._complete(key, lease, fitness[i], components[i], descriptors[i])
            self._errors.pop(credential(result.worker), None)
            record.jobs_done += 1
            record.evaluations += lease.stop - lease.start
            ack = Ack(key=result.key, accepted=True)
            following = key.at(key.generation + 1)
        if ack.accepted and self._store_lags(result.key.run_id):
            # a span ends with the message that took its run too far ahead of the store
            self._release_where(
                lambda lease: lease.key == following and lease.worker == result.worker
            )
        return ack

    def expire(self) -> int:
        """Return every lease past its deadline; forget workers gone long ago (but the
        quarantined). The count."""
        now = self._clock()
        with self._lock:
            released = self._release_where(lambda lease: lease.deadline <= now)
            for name, w in list(self._workers.items()):
                if (
                    w.gone_at is not None
                    and w.quarantine is None
                    and now - w.gone_at > self.policy.gone_keep_s
                ):
                    del self._workers[name]
        if released:
            self._announce()
        return len(released)

    def next_deadline(self) -> float | None:
        """The clock time of the next lease deadline, if any (the referee's have none)."""
        with self._lock:
            deadlines = (lease.deadline for lease in self._leases.values())
            return min((d for d in deadlines if d < math.inf), default=None)

    def totals(self) -> dict[str, int]:
        """Since construction: jobs `leased`, results accepted (`done`), leases returned
        (`requeued`) and results dropped as late or duplicate (`duplicates_dropped`)."""
        with self._lock:
            return dict(self._totals)

    def spot_totals(self) -> dict[str, int]:
        """Since construction: results spot-checked, individuals and robot-steps re-evaluated,
        and mismatches (each quarantined a worker)."""
        with self._lock:
            return dict(self._spot)

    def counts(self) -> dict[str, int]:
        """Jobs of the generations in flight by status: pending, leased, done."""
        counts = {"pending": 0, "leased": 0, "done": 0}
        with self._lock:
            for run in self._runs.values():
                for slot in run.slots:
                    counts[slot.status] += 1
        return counts

    # inside the lock -------------------------------------------------------------------------

    def _announce(self) -> None:
        with self._lock:
            listeners = list(self._listeners)
            ready = any(self._leasable(run) for run in self._runs.values())
        if ready:
            for listener in listeners:
                listener()

    def _leasable(self, run: _Run) -> bool:
        """Running, with a job pending, and its store keeping up."""
        return run.running and bool(run.pending) and not self._store_lags(run.run_id)

    def _store_lags(self, run_id: int) -> bool:
        """Whether the run's oldest unwritten generation has waited past `store_lag_s`."""
        times = self._unwritten.get(run_id)
        return times is not None and self._clock() - times[0] > self.policy.store_lag_s

    def _touch(self, worker: str, *, revive: bool = True) -> _Worker:
        """The worker's record, seen now; live again unless `revive` is False (a result
        arriving after its token vanished does not make it live: no token would end that)."""
        record = self._workers.get(worker)
        if record is None:
            record = self._workers[worker] = _Worker(worker)
            record.quarantine = self._banned.get(credential(worker))
        record.last_seen = self._wall()
        if revive:
            record.gone_at = None
        return record

    def _install(self, run_id: int, loop: RunLoop, running: bool, served: int) -> None:
        config = loop.config
        size = self._job_size(config, loop.generation, run_id if running else None)
        slots = [_Slot(a, b) for a, b in job_slices(config.population, size)]
        self._runs[run_id] = _Run(
            run_id=run_id,
            loop=loop,
            running=running,
            slots=slots,
            pending=list(range(len(slots))),
            fitness=np.full(config.population, np.nan),
            components=np.full((config.population, config.trials, 4), np.nan),
            descriptors=np.full((config.population, 4), np.nan),
            remaining=len(slots),
            served=served,
        )

    def _live(self) -> list[_Worker]:
        """Workers that take jobs: a token, and a lease held or asked for within
        `lease_max_s` (no lease lasts longer)."""
        since = self._clock() - self.policy.lease_max_s
        busy = {lease.worker for lease in self._leases.values()}
        return [
            w
            for w in self._workers.values()
            if w.gone_at is None
            and w.serving
            and w.quarantine is None
            and (w.name in busy or (w.asked_at is not None and w.asked_at >= since))
        ]

    def _crowded(self, run_id: int | None = None) -> bool:
        """At least as many running runs (`run_id` counted as one) as jobs the live workers
        take (`jobs_per_worker` each): each job can be a run's whole generation, so slicing a
        generation only adds round trips."""
        live = len(self._live()) * self.policy.jobs_per_worker
        running = {run.run_id for run in self._runs.values() if run.running}
        return live > 0 and len(running | ({run_id} if run_id is not None else set())) >= live

    def _job_size(self, config: RunConfig, generation: int, run_id: int | None) -> int:
        """One job per live worker (`jobs_per_worker` each, at least the run's `job_size`), or
        the whole generation when runs are crowded or whoever leases it will get a span: a
        whole generation leased to one worker would otherwise keep the others idle."""
        live = self._live()
        if not live:
            return config.job_size
        if self._crowded(run_id):
            return config.population
        speeds = [w.speed if w.spans else None for w in live]
        if (
            generation + 1 < config.generations
            and traits(config).in_state  # a worker evolves only the paper's GA itself
            and all(s is not None for s in speeds)
        ):
            slowest = min(s for s in speeds if s is not None)
            if self.policy.span_generations(config, slowest, crowded=False) > 1:
                return config.population
        jobs = len(live) * self.policy.jobs_per_worker
        return max(config.job_size, -(-config.population // jobs))

    def _lease(
        self,
        run: _Run,
        index: int,
        worker: str,
        *,
        span_left: int = 0,
        asked_by_worker: bool = False,
    ) -> float:
        """Lease slot `index` of the run's generation to `worker`; the lease's seconds, from
        the slot's robot-steps and the worker's speed."""
        slot = run.slots[index]
        config = run.loop.config
        lease_s = self.policy.lease_seconds(
            robot_steps(config, slot.stop - slot.start), self._workers[worker].measured
        )
        slot.status = "leased"
        self._sequence += 1
        run.served = self._sequence
        key = JobKey(run_id=run.run_id, generation=run.loop.generation, index=index)
        now = self._clock()
        self._leases[key] = _Lease(
            key, worker, now + lease_s, slot.start, slot.stop, now, span_left, asked_by_worker
        )
        self._totals["leased"] += 1
        return lease_s

    def _digest_error(self, result: Result, i: int, lease: _Lease, record: _Worker) -> str | None:
        """Why a span's generation cannot count (None if it can): the worker must have
        evaluated the genomes asked here, else its GA differs and it gets no more spans."""
        if not result.digests:
            if not lease.asked_by_worker:
                return None
            record.spans = False
            return "a span's generation without its digest"
        run = self._runs[lease.key.run_id]
        asked = run.loop.ask()[lease.start : lease.stop]
        if result.digests[i] == genome_digest(asked):
            return None
        record.spans = False
        return "evaluated other genomes than the server asked (its GA differs: another version?)"

    def _complete(
        self,
        key: JobKey,
        lease: _Lease,
        fitness: np.ndarray,
        components: np.ndarray,
        descriptors: np.ndarray,
    ) -> None:
        run = self._runs[key.run_id]
        slot = run.slots[key.index]
        self._count_errors(slot)
        run.fitness[slot.start : slot.stop] = fitness
        run.components[slot.start : slot.stop] = components
        run.descriptors[slot.start : slot.stop] = descriptors
        slot.status = "done"
        slot.worker = lease.worker
        run.remaining -= 1
        self._totals["done"] += 1
        if run.remaining:
            return
        loop = run.loop
        told = loop.tell(run.fitness, run.components, run.descriptors)
        candidates = loop.candidates(told.genomes, told.fitness) if loop.done else None
        self._told.append(Written(run.run_id, loop.config, told, loop.done, candidates))
        times = self._unwritten.setdefault(run.run_id, deque())
        times.append(self._clock())
        if len(times) >= self.policy.write_now:
            self.told_many.set()
        if loop.done:
            del self._runs[run.run_id]
            return
        self._install(run.run_id, loop, run.running, served=run.served)
        following = self._runs[run.run_id]
        if lease.span_left > 0 and following.running and len(following.slots) == 1:
            heapq.heappop(following.pending)
            self._lease(
                following, 0, lease.worker, span_left=lease.span_left - 1, asked_by_worker=True
            )

    def _spot_check(self, result: Result, record: _Worker) -> str | None:
        """Re-evaluate `spot_checks` individuals of `result`, drawn with `secrets` among the
        generations it may complete; why it fails (worker, run, generation, individual,
        claimed and recomputed), or None (it passed, or it counts for nothing anyway)."""
        wanted = self.policy.spot_checks
        lease = self._leases.get(result.key)
        run = self._runs.get(result.key.run_id)
        fitness, components, descriptors = result.fitness, result.components, result.descriptors
        if (
            wanted == 0
            or not record.listed
            or fitness is None
            or components is None
            or descriptors is None
            or lease is None
            or run is None
            or lease.worker != result.worker
            or (result.start, result.stop) != (lease.start, lease.stop)
        ):
            return None  # off, this process's own evaluator, an error, or dropped below
        n = lease.stop - lease.start
        loop = run.loop
        config = loop.config
        generations = 1  # then those `_complete` will move the span's lease on to
        while (
            generations < min(result.generations, lease.span_left + 1)
            and run.running
            and self._job_size(config, loop.generation + generations, run.run_id)
            >= config.population
        ):
            generations += 1
        picks = sorted(_CHOOSE.sample(range(generations * n), min(wanted, generations * n)))
        asked, shadow = loop.ask(), None
        self._spot["results_checked"] += 1
        for i in range(picks[-1] // n + 1):
            if i > 0:  # a span's later generation: the genomes its claimed fitness leads to
                shadow = shadow or RunLoop(config, state=loop.state)
                shadow.tell(fitness[i - 1], components[i - 1], descriptors[i - 1])
                asked = shadow.ask()
            rows = [p % n for p in picks if p // n == i]
            if not rows:
                continue
            generation = loop.generation + i
            again = evaluate(config, generation, asked[lease.start + np.array(rows)])
            self._spot["individuals_checked"] += len(rows)
            self._spot["robot_steps_checked"] += robot_steps(config, len(rows))
            for j, row in enumerate(rows):
                claimed = (fitness[i, row], components[i, row], descriptors[i, row])
                recomputed = (again.fitness[j], again.components[j], again.descriptors[j])
                for what, a, b in zip(_CHECKED, claimed, recomputed, strict=True):
                    if not _same_bits(a, b):
                        return (
                            f"worker {result.worker} run {run.run_id} generation {generation} "
                            f"individual {lease.start + row}: claimed {what} "
                            f"{np.asarray(a).tolist()!r}, recomputed {np.asarray(b).tolist()!r}"
                        )
        return None

    def _quarantine(self, name: str, why: str) -> None:
        """No more jobs for any worker of `name`'s credential; their leases and every result
        of them in the generations in flight return to pending."""
        banned = credential(name)
        self._banned[banned] = why
        for other in self._workers.values():
            if credential(other.name) == banned:
                other.quarantine = why
        released = self._release_where(lambda lease: credential(lease.worker) == banned)
        discarded = 0
        for run in self._runs.values():
            for index, slot in enumerate(run.slots):
                if slot.status == "done" and slot.worker and credential(slot.worker) == banned:
                    run.fitness[slot.start : slot.stop] = np.nan
                    run.components[slot.start : slot.stop] = np.nan
                    run.remaining += 1
                    slot.worker = None
                    self._make_pending(run, index)
                    discarded += 1
        context(log, worker=name).warning(
            "worker %s quarantined: %s; %d leases and %d results of it returned to pending",
            name,
            why,
            len(released),
            discarded,
        )

    def _erred(self, key: JobKey, record: _Worker, error: str) -> None:
        """`record`'s evaluation of the job `key` erred: the run fails if it is the server's
        own; else the job goes to another credential, or to the referee when none is left. The
        error counts against the credential once someone evaluates the job without one."""
        run = self._runs.get(key.run_id)
        if run is None:
            return
        if not record.listed:  # an in-process executor: this process's own evaluation
            self._fail_run(key, error)
            return
        slot = run.slots[key.index]
        slot.erred[credential(record.name)] = (record.name, error)
        run.erred = True
        self._make_pending(run, key.index)
        context(log, run=key.run_id, worker=record.name).warning(
            "worker %s: error result for run %d job %d/%d, which returns to other workers: %s",
            record.name,
            key.run_id,
            key.generation,
            key.index,
            error,
        )
        self._referee_stranded()

    def _count_errors(self, slot: _Slot) -> None:
        """The slot's job is evaluated without an error: each credential that erred on it
        erred on its own account, and `errors_quarantine` such errors in a row quarantine it."""
        for banned, (name, error) in slot.erred.items():
            errors = self._errors[banned] = self._errors.get(banned, 0) + 1
            if errors >= self.policy.errors_quarantine and banned not in self._banned:
                self._quarantine(
                    name,
                    f"worker {name}: {errors} error results in a row on jobs evaluated "
                    f"without one, the last: {error}",
                )
        slot.erred = {}

    def _fail_run(self, key: JobKey, error: str) -> None:
        self._failed[key.run_id] = (
            f"job {key.generation}/{key.index} failed in the server's own evaluation: {error}"
        )
        self._drop_run(key.run_id)

    def _pick(self, run: _Run, excluded: str | None) -> int | None:
        """The lowest pending slot of `run` not erred on by the credential `excluded`."""
        if not run.erred or excluded is None:
            return run.pending[0] if run.pending else None
        return min((i for i in run.pending if excluded not in run.slots[i].erred), default=None)

    @staticmethod
    def _unpend(run: _Run, index: int) -> None:
        if run.pending[0] == index:
            heapq.heappop(run.pending)
        else:
            run.pending.remove(index)
            heapq.heapify(run.pending)

    def _referee_stranded(self) -> None:
        """Lease to the referee every pending job that erred on `max_attempts` credentials or
        that no live worker may take (each live credential erred on it)."""
        live = self._live()  # an in-process executor takes any job
        takers = None if any(not w.listed for w in live) else {credential(w.name) for w in live}
        for run in self._runs.values():
            if not run.erred or not run.running:
                continue
            for index in list(run.pending):
                erred = run.slots[index].erred
                if erred and (
                    len(erred) >= self.policy.max_attempts
                    or (takers is not None and not takers - erred.keys())
                ):
                    self._refer(run, index)

    def _refer(self, run: _Run, index: int) -> None:
        """Lease pending slot `index` to the referee, whose thread evaluates it here (it
        stays pending if the referee has stopped: the scheduler is closing)."""
        slot = run.slots[index]
        loop = run.loop
        key = JobKey(run_id=run.run_id, generation=loop.generation, index=index)
        job = Job(
            key=key,
            start=slot.start,
            stop=slot.stop,
            config=loop.config,
            genomes=loop.ask()[slot.start : slot.stop],
            lease_s=self.policy.lease_max_s,
        )
        lease = _Lease(key, REFEREE, math.inf, slot.start, slot.stop, self._clock())
        try:
            self._referee.submit(self._judge, job, lease)  # it waits for this lock
        except RuntimeError:
            return
        self._unpend(run, index)
        slot.status = "leased"
        self._leases[key] = lease
        context(log, run=run.run_id).info(
            "run %d job %d/%d erred on %s: the server evaluates it",
            run.run_id,
            key.generation,
            index,
            ", ".join(sorted(slot.erred)),
        )

    def _judge(self, job: Job, lease: _Lease) -> None:
        """The referee's thread: evaluate `job` and settle it, or fail its run; nothing if
        `lease` ended meanwhile (its run dropped, replaced or resumed anew)."""
        with self._lock:
            if self._leases.get(job.key) is not lease:
                return
        result = run_job(job, "server")  # the lease stays REFEREE's, no worker's name
        try:
            with self._lock:
                if self._leases.get(job.key) is not lease:
                    return
                del self._leases[job.key]
                if (
                    result.fitness is None
                    or result.components is None
                    or result.descriptors is None
                ):
                    self._fail_run(job.key, result.error or "no evaluation")
                else:
                    self._complete(
                        job.key, lease, result.fitness[0], result.components[0],
                        result.descriptors[0],
                    )  # fmt: skip
        except Exception as exc:  # a bug here must fail the run, not leave its job held
            log.exception("the server's evaluation of run %d could not be recorded", job.key.run_id)
            with self._lock:
                if job.key.run_id in self._runs:
                    self._fail_run(job.key, f"the server's evaluation could not be recorded: {exc}")
        self._announce()

    def _drop_run(self, run_id: int) -> None:
        self._runs.pop(run_id, None)
        self._unwritten.pop(run_id, None)
        self._drop_leases(run_id)

    def _drop_leases(self, run_id: int) -> None:
        for key in [k for k in self._leases if k.run_id == run_id]:
            del self._leases[key]

    def _release_where(self, condition: Callable[[_Lease], bool]) -> list[JobKey]:
        released = [lease for lease in self._leases.values() if condition(lease)]
        for lease in released:
            del self._leases[lease.key]
            run = self._runs.get(lease.key.run_id)
            if run is not None and run.loop.generation == lease.key.generation:
                self._make_pending(run, lease.key.index)
        self._totals["requeued"] += len(released)
        return [lease.key for lease in released]

    @staticmethod
    def _make_pending(run: _Run, index: int) -> None:
        slot = run.slots[index]
        if slot.status != "pending":
            slot.status = "pending"
            heapq.heappush(run.pending, index)


def _same_bits(claimed: np.ndarray, recomputed: np.ndarray) -> bool:
    """Bit for bit: a deterministic evaluation repeats every byte (-0.0 and NaN payloads too)."""
    a = np.ascontiguousarray(claimed, dtype="<f8")
    b = np.ascontiguousarray(recomputed, dtype="<f8")
    return a.shape == b.shape and a.tobytes() == b.tobytes()


_CHECKED = ("fitness", "components", "descriptors")
"""What a spot-check compares bit for bit, in this order."""
