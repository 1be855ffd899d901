"""The simulation worker: pull a job, evaluate its whole slice at once, return the result.

A client zenoh session to the server's router (retried with backoff until one is reachable;
zenoh itself reconnects a live session after a server restart), a liveliness token
`evocolony/workers/NAME`, then the loop of docs/protocol.md. Every job is validated before it
runs; a bad job or a failing evaluation becomes an error result, never a crash. A stop request
(SIGINT, SIGTERM) lets the current job finish and its result go back, then the worker exits.
A span is evolved here generation after generation by the run loop of `evorobotics`, the one
the server drives. A job of a finished run's champion (`Job.key.stage`) scores its candidates
on the validation set or its test poses; a report's job, trials of a controller's exploration
report or robustness map.

Hierarchy:
    WorkerError          the worker's own errors
    └── EvaluationError  the evaluator returned shapes or values a result cannot carry
"""

from __future__ import annotations

import logging
import os
import re
import signal
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from types import FrameType

import numpy as np
import zenoh

from evorobotics.evaluate import robot_steps
from evorobotics.evolution import RunLoop
from evorobotics.ga import GAState
from evorobotics.reports import stage_scores, stage_steps
from schemas.answer import CONSOLIDATION, TARGET, one_answer
from schemas.run import RunConfig
from schemas.security import ZenohClientAuth
from schemas.wire import (
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    SPAN_BATCH_MAX,
    Idle,
    InvalidJobError,
    Job,
    JobRequest,
    Result,
    WireError,
    check_worker_name,
    decode_next_reply,
    decode_result_reply,
    encode,
    genome_digest,
    next_key,
    result_key,
    worker_key,
)

log = logging.getLogger(__name__)

SPAN_SEND_S = 0.25
"""A span's results go to the server at least this often (several generations a message):
each message costs the server a round trip and a spot-check, so a span of the paper's short
generations sends a dozen or more a message (a study of 8 runs of 100 paper generations on 2
workers: the server's CPU per run 0.7x what messages every 0.05 s cost it)."""
SPAN_WINDOW = 4
"""A span's messages sent but not yet acknowledged before the worker waits for the oldest."""

Evaluated = tuple[np.ndarray, np.ndarray, np.ndarray]
"""fitness (n,), components (n, trials, 4), descriptors (n, 4) of n genomes."""
Evaluator = Callable[[RunConfig, int, np.ndarray], Evaluated]
"""(config, generation, genomes (n, w)) -> their `Evaluated`."""


class WorkerError(Exception):
    """Root of the worker's own errors."""


class EvaluationError(WorkerError):
    """The evaluator returned shapes or values a result cannot carry."""


def evaluate_slice(
    config: RunConfig, generation: int, genomes: np.ndarray, *, threads: int = 1
) -> Evaluated:
    """The science: `evorobotics.evaluate.evaluate` over the whole slice, vectorised, on
    `threads` threads (the same bits whatever the count)."""
    from evorobotics.evaluate import evaluate

    evaluation = evaluate(config, generation, genomes, threads=threads)
    return evaluation.fitness, evaluation.components, evaluation.descriptors


def default_name(user: str | None = None) -> str:
    """hostname-pid, reduced to the characters a key chunk allows; `user.hostname-pid` with a
    zenoh user, the names that user's credentials may use (docs/security.md)."""
    host = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname())[:100] or "worker"
    name = f"{host}-{os.getpid()}"
    return name if user is None else f"{user}.{name}"[:128]


@dataclass(frozen=True)
class WorkerSettings:
    """Where the server is and how patiently to talk to it."""

    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    name: str = field(default_factory=default_name)
    request_timeout_s: float = 10.0
    """Timeout of each `get`; above the server's long-poll (1 s) plus the job's transfer."""
    backoff_initial_s: float = 0.1
    backoff_max_s: float = 5.0
    multicast_scouting: bool = False
    threads: int = 1
    """Threads a job's evaluation runs on (the same results whatever the count)."""
    auth: ZenohClientAuth = field(default_factory=ZenohClientAuth)
    """zenoh user/password and TLS root CA (docs/security.md)."""

    def __post_init__(self) -> None:
        check_worker_name(self.name)
        user = self.auth.user
        if user is not None and self.name != user and not self.name.startswith(f"{user}."):
            raise ValueError(
                f"worker name {self.name!r} must be {user!r} or start with '{user}.': the zenoh "
                f"user {user} may only act under its own names"
            )
        if not self.connect:
            raise ValueError("a worker needs at least one connect endpoint")
        if not 1 <= self.threads <= 256:
            raise ValueError(f"threads must be 1 to 256, got {self.threads}")
        for name in ("request_timeout_s", "backoff_initial_s", "backoff_max_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")

    def zenoh_config(self) -> zenoh.Config:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", "[" + ",".join(f'"{e}"' for e in self.connect) + "]")
        conf.insert_json5(
            "scouting/multicast/enabled", "true" if self.multicast_scouting else "false"
        )
        # zenoh's shared memory maps a 16 MiB pool per session for messages over 3 KiB: a cost,
        # not a gain, for jobs of a few KiB (docs/reliability.md, "Load")
        conf.insert_json5("transport/shared_memory/enabled", "false")
        for key, value in self.auth.entries():
            conf.insert_json5(key, value)
        return conf


@dataclass
class WorkerStats:
    """What a worker did, returned when it stops."""

    jobs_done: int = 0
    evaluations: int = 0
    """Controllers evaluated (each over the run's trials), sent or not."""
    errors: int = 0
    robot_steps_per_s: float | None = None


class _Backoff:
    def __init__(self, settings: WorkerSettings) -> None:
        self._settings = settings
        self._delay = settings.backoff_initial_s

    def next(self) -> float:
        delay = self._delay
        self._delay = min(self._delay * 2, self._settings.backoff_max_s)
        return delay

    def reset(self) -> None:
        self._delay = self._settings.backoff_initial_s


def run_worker(
    settings: WorkerSettings,
    stop: threading.Event,
    *,
    evaluator: Evaluator | None = None,
) -> WorkerStats:
    """Serve jobs until `stop` is set; open (and reopen) the session as needed. Jobs are
    evaluated by `evaluator`, by default the science on `settings.threads` threads."""
    evaluator = evaluator or partial(evaluate_slice, threads=settings.threads)
    stats = WorkerStats()
    backoff = _Backoff(settings)
    host = socket.gethostname()
    while not stop.is_set():
        try:
            session = zenoh.open(settings.zenoh_config())
        except zenoh.ZError as exc:
            delay = backoff.next()
            log.info("no router at %s (%s); retrying in %.1f s", settings.connect, exc, delay)
            stop.wait(delay)
            continue
        try:
            token = session.liveliness().declare_token(worker_key(settings.name))
            try:
                link = _Link(session, settings, stop, stats)
                try:
                    log.info("worker %s connected to %s", settings.name, settings.connect)
                    _serve(link, host, evaluator, backoff)
                finally:
                    link.close()
            finally:
                token.undeclare()  # type: ignore[no-untyped-call]
        finally:
            session.close()  # type: ignore[no-untyped-call]
    return stats


class _Link:
    """The worker's side of a session: one querier per key it asks the server on (a
    querier's `get` costs less than the session's), with what every call needs."""

    def __init__(
        self,
        session: zenoh.Session,
        settings: WorkerSettings,
        stop: threading.Event,
        stats: WorkerStats,
    ) -> None:
        self.settings, self.stop, self.stats = settings, stop, stats
        self._queriers = {
            key: session.declare_querier(
                name, timeout=settings.request_timeout_s, target=TARGET, consolidation=CONSOLIDATION
            )
            for key, name in (
                (KEY_JOB_NEXT, next_key(settings.name)),
                (KEY_JOB_RESULT, result_key(settings.name)),
            )
        }

    def get(self, key: str, payload: bytes) -> zenoh.Handler[zenoh.Reply]:
        """Send a query now; its replies are read later."""
        return self._queriers[key].get(payload=payload)

    def ask(self, key: str, payload: bytes) -> bytes | None:
        """The server's successful reply's payload (waiting for it), or None."""
        return one_answer(self.get(key, payload), key, log)

    def close(self) -> None:
        for querier in self._queriers.values():
            querier.undeclare()  # type: ignore[no-untyped-call]


def _serve(link: _Link, host: str, evaluator: Evaluator, backoff: _Backoff) -> None:
    """Ask, evaluate, deliver asking for the next, until stopped."""
    job: Job | None = None
    while not link.stop.is_set():
        if job is None:
            job = _next_job(link, host, backoff)
        elif job.span > 1:
            job = _evolve_span(link, job, evaluator)
        elif job.key.stage != "train":
            job = _deliver(link, _score(link, job))
        else:
            job = _deliver(link, _evaluate(link, job, evaluator))


def _next_job(link: _Link, host: str, backoff: _Backoff) -> Job | None:
    """One `get` on jobs/next: a job, or None (idle, no server, or a job it reported invalid)."""
    settings = link.settings
    request = JobRequest(
        worker=settings.name,
        host=host[:255],
        robot_steps_per_s=link.stats.robot_steps_per_s,
        threads=settings.threads,
    )
    reply = link.ask(KEY_JOB_NEXT, encode(request))
    if reply is None:
        link.stop.wait(backoff.next())
        return None
    backoff.reset()
    try:
        job = decode_next_reply(reply)
    except InvalidJobError as exc:
        return _reject_job(link, exc)
    except WireError as exc:
        log.warning("dropping malformed reply: %s", exc)
        link.stop.wait(backoff.next())
        return None
    return None if isinstance(job, Idle) else job


def _reject_job(link: _Link, exc: InvalidJobError) -> Job | None:
    log.warning("rejecting invalid job: %s", exc)
    link.stats.errors += 1
    return _deliver(link, Result(key=exc.key, worker=link.settings.name, error=exc.reason))


def _evaluate(
    link: _Link, job: Job, evaluator: Evaluator, genomes: np.ndarray | None = None
) -> Result:
    """One generation of `job` (of `genomes` if given: a span's own), its checks after its
    slice, as a Result."""
    if genomes is None:
        genomes = job.evaluated()
    began = time.perf_counter()
    try:
        fitness, components, descriptors = _checked(
            evaluator(job.config, job.key.generation, genomes), job, len(genomes)
        )
    except Exception as exc:  # report it to the server instead of crashing the worker
        return _failed(link, job, "evaluating", exc)
    seconds = time.perf_counter() - began
    speed = robot_steps(job.config, len(genomes)) / seconds if seconds > 0 else None
    link.stats.jobs_done += 1
    link.stats.evaluations += job.stop - job.start  # its slice: checks are no run's
    link.stats.robot_steps_per_s = speed
    return Result(
        key=job.key,
        worker=link.settings.name,
        start=job.start,
        stop=job.stop,
        robot_steps_per_s=speed or 0.0,
        seconds=seconds,
        checks=len(genomes) - (job.stop - job.start),
        fitness=fitness[np.newaxis],
        components=components[np.newaxis],
        descriptors=descriptors[np.newaxis],
    )


def _failed(link: _Link, job: Job, doing: str, exc: Exception) -> Result:
    """The error Result of a job whose evaluation raised, logged with its traceback."""
    log.exception("%s %s failed", doing, job.key.label())
    link.stats.errors += 1
    error = f"{type(exc).__name__}: {exc}"
    return Result(
        key=job.key, worker=link.settings.name, error=error, start=job.start, stop=job.stop
    )


def _score(link: _Link, job: Job) -> Result:
    """A champion stage's job (validation candidates or test poses) or a report's (trials) as
    a Result: the science itself (`stage_scores`), whatever the evaluator."""
    began = time.perf_counter()
    stage, report = job.key.stage, job.report
    try:
        scores = stage_scores(job.config, stage, job.genomes, job.start, job.stop, report)
    except Exception as exc:  # report it to the server instead of crashing the worker
        return _failed(link, job, "scoring", exc)
    seconds = time.perf_counter() - began
    steps = stage_steps(job.config, stage, job.stop - job.start, report)
    speed = steps / seconds if seconds > 0 else None
    link.stats.jobs_done += 1
    link.stats.robot_steps_per_s = speed
    return Result(
        key=job.key,
        worker=link.settings.name,
        start=job.start,
        stop=job.stop,
        robot_steps_per_s=speed or 0.0,
        seconds=seconds,
        scores=scores,
    )


def _checked(out: Evaluated, job: Job, n: int) -> Evaluated:
    """The evaluator's fitness (n,), components (n, trials, 4) and descriptors (n, 4) as
    float64."""
    fitness, components, descriptors = (np.ascontiguousarray(a, dtype=np.float64) for a in out)
    trials = job.config.trials
    if (fitness.shape, components.shape, descriptors.shape) != ((n,), (n, trials, 4), (n, 4)):
        raise EvaluationError(
            f"evaluator returned {fitness.shape}, {components.shape} and {descriptors.shape} "
            f"for {n}"
        )
    if not np.isfinite(fitness).all():
        raise EvaluationError("evaluator returned non-finite fitness")
    return fitness, components, descriptors


def _evolve_span(link: _Link, job: Job, evaluator: Evaluator) -> Job | None:
    """Evolve the span's generations here with the run loop, sending results as it goes; the
    next job if the server sent one with the acknowledgement of an error.

    Results go out every SPAN_SEND_S (several generations a message) without waiting for
    their acknowledgement (up to SPAN_WINDOW messages), so the server records generations
    while this worker evaluates the next. Each carries the digest of the genomes this worker
    asked. The span ends early when stopping, or when a result is refused or unanswered (the
    run paused or ended, the lease expired, the server restarted): the server re-leases from
    the last generation it recorded, so a generation evolved twice still counts once.
    """
    try:
        loop = RunLoop(job.config, GAState.from_arrays(job.state or {}))
        if loop.generation != job.key.generation:
            raise ValueError(f"state of generation {loop.generation}")
        loop.ask()  # a state that does not fit the run (its population) fails here
    except ValueError as exc:
        link.stats.errors += 1
        error = f"span of {job.key.label()} has an unusable GA state: {exc}"
        return _deliver(
            link,
            Result(
                key=job.key, worker=link.settings.name, error=error, start=job.start, stop=job.stop
            ),
        )
    in_flight: deque[tuple[Job, zenoh.Handler[zenoh.Reply]]] = deque()
    batch: list[tuple[Result, str]] = []
    sent_at = time.monotonic()

    def send() -> None:
        first = batch[0][0]
        fitness = [r.fitness for r, _ in batch if r.fitness is not None]
        components = [r.components for r, _ in batch if r.components is not None]
        descriptors = [r.descriptors for r, _ in batch if r.descriptors is not None]
        result = first.model_copy(
            update={
                "fitness": np.concatenate(fitness),
                "components": np.concatenate(components),
                "descriptors": np.concatenate(descriptors),
                "digests": tuple(d for _, d in batch),
                "seconds": sum(r.seconds for r, _ in batch),
                "robot_steps_per_s": batch[-1][0].robot_steps_per_s,
            }
        )
        in_flight.append((job, link.get(KEY_JOB_RESULT, encode(result))))
        batch.clear()

    for offset in range(job.span):
        current = job.model_copy(update={"key": job.key.at(loop.generation), "span": 1})
        genomes = loop.ask()
        result = _evaluate(link, current, evaluator, genomes)
        if result.fitness is None or result.components is None or result.descriptors is None:
            if batch:  # the generations before it count; the failed one is retried
                send()
            return _deliver(link, result)
        batch.append((result, genome_digest(genomes)))
        last = link.stop.is_set() or offset + 1 == job.span
        if last or len(batch) == SPAN_BATCH_MAX or time.monotonic() - sent_at >= SPAN_SEND_S:
            send()
            sent_at = time.monotonic()
            if not _span_acks(in_flight, keep=SPAN_WINDOW):
                return None
        if last:
            break
        loop.tell(result.fitness[0], result.components[0], result.descriptors[0])
    _span_acks(in_flight, keep=0)
    return None


def _span_acks(in_flight: deque[tuple[Job, zenoh.Handler[zenoh.Reply]]], keep: int) -> bool:
    """Take the acknowledgements that have come, waiting for the oldest while more than
    `keep` are outstanding; False (and the rest abandoned) once one is refused or missing."""
    while in_flight:
        job, replies = in_flight[0]
        if len(in_flight) > keep:
            payload = one_answer(replies, KEY_JOB_RESULT, log)
        else:
            try:
                reply = replies.try_recv()
            except zenoh.ZError:  # finished without a reply
                payload = None
            else:
                if reply is None:
                    return True
                payload = None if reply.ok is None else reply.ok.payload.to_bytes()
        in_flight.popleft()
        try:
            ack = None if payload is None else decode_result_reply(payload)[0]
        except WireError as exc:
            log.warning("malformed acknowledgement in a span of %s: %s", job.key.label(), exc)
            ack = None
        if ack is None or not ack.accepted:
            reason = "no answer" if ack is None else ack.reason or "refused"
            log.info("span of %s ends: %s", job.key.label(), reason)
            in_flight.clear()
            return False
    return True


def _deliver(link: _Link, result: Result) -> Job | None:
    """Send `result` until acknowledged; the next job if the server sent one with the Ack.

    Unless stopping, the result asks for the next job, saving a round trip. Once stopping,
    two more tries, then the lease lapses on the server.
    """
    backoff = _Backoff(link.settings)
    tries_after_stop = 0
    while tries_after_stop < 2:
        asking = result.model_copy(update={"want_next": not link.stop.is_set()})
        reply = link.ask(KEY_JOB_RESULT, encode(asking))
        if reply is not None:
            try:
                ack, job = decode_result_reply(reply)
            except InvalidJobError as exc:
                if exc.ack is not None and exc.ack.key == result.key:
                    return _reject_job(link, exc)
                log.warning("malformed acknowledgement for %s: %s", result.key.label(), exc)
            except WireError as exc:
                log.warning("malformed acknowledgement for %s: %s", result.key.label(), exc)
            else:
                if ack.key == result.key:
                    if not ack.accepted:
                        log.info("%s dropped by the server: %s", result.key.label(), ack.reason)
                    return job
        if link.stop.is_set():
            tries_after_stop += 1
        link.stop.wait(backoff.next())
    log.warning("gave up delivering %s while stopping", result.key.label())
    return None


def install_signal_handlers(stop: threading.Event) -> None:
    """SIGINT and SIGTERM set `stop`: the current job finishes and goes back, then exit."""

    def handler(signum: int, _frame: FrameType | None) -> None:
        log.info("signal %d: finishing the current job, then exiting", signum)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def watch_parent(stop: threading.Event, interval_s: float = 0.5) -> threading.Thread:
    """Set `stop` when the parent process dies (we get re-parented), so a SIGKILLed server's
    local workers finish their job and exit instead of running forever."""
    if interval_s <= 0:
        raise ValueError(f"interval_s must be > 0, got {interval_s}")
    parent = os.getppid()

    def watch() -> None:
        while not stop.wait(interval_s):
            if os.getppid() != parent:
                log.warning("parent process %d is gone; stopping", parent)
                stop.set()

    thread = threading.Thread(target=watch, name="parent-watch", daemon=True)
    thread.start()
    return thread
