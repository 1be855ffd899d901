"""The simulation worker: pull a job, evaluate its whole slice at once, return the result.

A client zenoh session to the server's router (retried with backoff until one is reachable;
zenoh itself reconnects a live session after a server restart), a liveliness token
`evocolony/workers/NAME`, then the loop of docs/protocol.md. Every job is validated before it
runs; a bad job or a failing evaluation becomes an error result, never a crash. A stop request
(SIGINT, SIGTERM) lets the current job finish and its result go back, then the worker exits.
A span (protocol 5) is evolved here generation after generation, with the GA of `evorobotics`,
alone or split with other workers in a team (protocol 7, `worker.team`).
"""

from __future__ import annotations

import itertools
import logging
import os
import re
import signal
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from types import FrameType

import numpy as np
import zenoh

from evorobotics.ga import GAParams, GAState, ask, ga_rng, tell
from evorobotics.layout import Layout, layout
from schemas.run import RunConfig
from schemas.security import ZenohClientAuth
from schemas.wire import (
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    SPAN_BATCH_MAX,
    Idle,
    InvalidJobError,
    Job,
    JobKey,
    JobRequest,
    Result,
    WireError,
    check_worker_name,
    decode_next_reply,
    decode_result_reply,
    encode_message,
    encode_result,
    encode_span_results,
    genome_digest,
    worker_key,
)
from worker import shared
from worker.shared import SharedTeam
from worker.team import Evaluator, Inbox, Team, checked_evaluation

log = logging.getLogger(__name__)

SPAN_SEND_S = 0.05
"""A span's results go to the server at least this often (several generations a message)."""
SPAN_WINDOW = 4
"""A span's messages sent but not yet acknowledged before the worker waits for the oldest."""
PIPELINE = 2
"""Requests that may bring a job in flight at once (protocol 9): a result asks for the next job
before the reply to the previous request is read, so the worker never waits out a round trip
with nothing sent. Empty jobs: two gave about 30 % more a second than one; three, no more."""


def evaluate_slice(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The science: `evorobotics.evaluate.evaluate` over the whole slice, vectorised."""
    from evorobotics.evaluate import evaluate

    evaluation = evaluate(config, generation, genomes)
    return evaluation.fitness, evaluation.components


def default_name() -> str:
    """hostname-pid, reduced to the characters a key chunk allows."""
    host = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname())[:100] or "worker"
    return f"{host}-{os.getpid()}"


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
    auth: ZenohClientAuth = field(default_factory=ZenohClientAuth)
    """zenoh user/password and TLS root CA (docs/security.md)."""

    def __post_init__(self) -> None:
        check_worker_name(self.name)
        if not self.connect:
            raise ValueError("a worker needs at least one connect endpoint")
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
    evaluator: Evaluator = evaluate_slice,
) -> WorkerStats:
    """Serve jobs until `stop` is set; open (and reopen) the session as needed."""
    stats = WorkerStats()
    backoff = _Backoff(settings)
    host = socket.gethostname()
    # request numbers (protocol 9) run on across sessions, and start from the clock in
    # microseconds: neither a reopened session's nor a restarted worker's (same name) can be
    # taken for earlier ones
    numbers = itertools.count(time.time_ns() // 1000)
    if shared.supported():
        try:
            shared.sweep()
        except OSError as exc:  # housekeeping: never a reason not to serve
            log.warning("could not sweep /dev/shm for left-over team files: %s", exc)
    while not stop.is_set():
        try:
            session = zenoh.open(settings.zenoh_config())
        except zenoh.ZError as exc:
            delay = backoff.next()
            log.info("no router at %s (%s); retrying in %.1f s", settings.connect, exc, delay)
            stop.wait(delay)
            continue
        try:
            inbox = Inbox(session, settings.name)
            token = session.liveliness().declare_token(worker_key(settings.name))
            try:
                link = _Link(session, settings.request_timeout_s, numbers)
                try:
                    log.info("worker %s connected to %s", settings.name, settings.connect)
                    _serve(link, settings, host, stop, evaluator, stats, backoff, inbox)
                finally:
                    link.close()
            finally:
                token.undeclare()  # type: ignore[no-untyped-call]
                inbox.close()
        finally:
            session.close()  # type: ignore[no-untyped-call]
    return stats


class _Link:
    """The worker's session with a querier declared once per key it asks the server on: a
    querier's `get` costs less than the session's (a job and a result every round trip: about
    7 % more empty jobs a second, measured). It numbers the requests that may bring a job and
    knows which of them are unanswered (protocol 9), from `numbers`, which outlives a session."""

    def __init__(self, session: zenoh.Session, timeout_s: float, numbers: Iterator[int]) -> None:
        self.session = session
        self._queriers = {
            key: session.declare_querier(key, timeout=timeout_s)
            for key in (KEY_JOB_NEXT, KEY_JOB_RESULT)
        }
        self._numbers = numbers
        self._awaiting: dict[int, None] = {}
        """Numbers of requests sent whose replies are not read yet, oldest first."""

    def get(self, key: str, payload: bytes) -> zenoh.Handler[zenoh.Reply]:
        """Send an unnumbered query now (a span's results); its replies are read later."""
        return self._queriers[key].get(payload=payload)

    def ask(self, key: str, build: Callable[[int, tuple[int, ...]], bytes]) -> _Pending:
        """Send the request `build(seq, awaiting)` makes for a new number; read it with `read`."""
        seq = next(self._numbers)
        payload = build(seq, tuple(self._awaiting))
        pending = _Pending(self._queriers[key].get(payload=payload), key, seq)
        self._awaiting[seq] = None
        return pending

    def read(self, pending: _Pending) -> bytes | None:
        """The first successful reply's payload (waiting for it), or None; answered then."""
        try:
            return _first_ok(pending.replies, pending.key)
        finally:
            self._awaiting.pop(pending.seq, None)

    def close(self) -> None:
        for querier in self._queriers.values():
            querier.undeclare()  # type: ignore[no-untyped-call]


@dataclass
class _Pending:
    """A numbered request sent; its replies are read once, by `_Link.read`."""

    replies: zenoh.Handler[zenoh.Reply]
    key: str
    seq: int


@dataclass
class _Ahead:
    """A request in flight while jobs are evaluated: a prefetch on jobs/next (`result` None)
    or a result whose reply may carry the next job."""

    pending: _Pending
    result: Result | None


def _serve(
    link: _Link,
    settings: WorkerSettings,
    host: str,
    stop: threading.Event,
    evaluator: Evaluator,
    stats: WorkerStats,
    backoff: _Backoff,
    inbox: Inbox,
) -> None:
    """Evaluate jobs with the next ones already asked for (protocols 3 and 9).

    While a job is evaluated, requests are in flight: a prefetch of the next job (unless the
    server said it could only come back idle), or earlier results asking for the next. Each
    result goes out asking for the next job as soon as it is known; the worker then reads the
    oldest reply only once `PIPELINE` requests are in flight (or it needs that reply's job to go
    on). So in steady state a worker never waits for a round trip between jobs. Once stopping,
    no prefetch: the job in evaluation is delivered, a prefetched one is left to lapse
    (released when the liveliness token goes).
    """
    in_hand: deque[Job] = deque()
    ahead: deque[_Ahead] = deque()

    def collect() -> None:
        in_hand.extend(_collect(link, settings, stop, stats, ahead.popleft(), in_hand))

    while not stop.is_set():
        if not in_hand:
            if ahead:
                collect()
                continue
            job = _next_job(link, settings, host, stop, stats, backoff)
            if job is None:
                continue
            in_hand.append(job)
        if in_hand[0].span > 1 and ahead:  # replies first, with the span held meanwhile
            collect()
            continue
        job = in_hand.popleft()
        if job.span > 1:
            following = _evolve_span(link, settings, stop, job, evaluator, stats, inbox)
            if following is not None:
                in_hand.append(following)
            continue
        if not ahead and not in_hand and job.more:
            held = (job.key,)
            ahead.append(
                _Ahead(link.ask(KEY_JOB_NEXT, _request(settings, host, stats, held)), None)
            )
        result = _evaluate(job, settings.name, evaluator, stats)
        if stop.is_set():
            while ahead:
                collect()
            _deliver(link, settings, stop, result, stats, tuple(j.key for j in in_hand))
            break
        holding = tuple(j.key for j in in_hand)
        ahead.append(_Ahead(link.ask(KEY_JOB_RESULT, _asking(result, True, holding)), result))
        # without `more` the server has no job to spare: the reply is read before going on
        while len(ahead) >= PIPELINE or (ahead and not in_hand and not job.more):
            collect()
    while ahead:
        _collect(link, settings, stop, stats, ahead.popleft(), in_hand)


def _request(
    settings: WorkerSettings, host: str, stats: WorkerStats, holding: tuple[JobKey, ...] = ()
) -> Callable[[int, tuple[int, ...]], bytes]:
    """A `jobs/next` request holding `holding`, for `_Link.ask` to number."""

    def build(seq: int, awaiting: tuple[int, ...]) -> bytes:
        request = JobRequest(
            worker=settings.name,
            host=host[:255],
            machine=shared.machine(),
            robot_steps_per_s=stats.robot_steps_per_s,
            holding=holding,
            seq=seq,
            awaiting=awaiting,
        )
        return encode_message(request)

    return build


def _asking(
    result: Result, want_next: bool, holding: tuple[JobKey, ...]
) -> Callable[[int, tuple[int, ...]], bytes]:
    """`result` as delivered, for `_Link.ask` to number."""

    def build(seq: int, awaiting: tuple[int, ...]) -> bytes:
        return encode_result(result.asking(want_next, holding, seq, awaiting))

    return build


def _evolve_span(
    link: _Link,
    settings: WorkerSettings,
    stop: threading.Event,
    job: Job,
    evaluator: Evaluator,
    stats: WorkerStats,
    inbox: Inbox,
) -> Job | None:
    """Evolve the span's generations here, sending their results as it goes; the next job
    if the server sent one with the acknowledgement of an error.

    In a team, each generation is split between the members (`worker.team`, or
    `worker.shared` on one machine); a member other than the leader sends the server nothing.

    Results go out every SPAN_SEND_S (several generations a message) without waiting for
    their acknowledgement (up to SPAN_WINDOW messages), so the server records generations
    while this worker evaluates the next. Each carries the digest of the genomes this worker
    asked, checked against the server's. The span ends early when stopping, or when a result
    is refused or unanswered (the lease moved on: the run paused or ended, the lease expired,
    the server restarted): the server re-leases from the last generation it recorded, so a
    generation evolved twice still counts once.
    """
    config = job.config
    team = _join_team(link.session, inbox, job, evaluator)
    if job.member > 0 and team is None:
        return None  # the leader evaluates this worker's slice itself
    try:
        if isinstance(team, SharedTeam) and not team.leader:
            _help(team, stop, stats)
            return None
        try:
            params, spec_layout = GAParams.from_config(config), layout(config.network_spec)
            state = GAState.from_arrays(job.state or {})
            if (state.generation, state.n_weights) != (job.key.generation, spec_layout.n_weights):
                raise ValueError(
                    f"state of generation {state.generation} with {state.n_weights} weights "
                    f"for generation {job.key.generation} of a {spec_layout.n_weights}-weight "
                    "network"
                )
        except ValueError as exc:
            error = f"span of {job.key.label()} has an unusable GA state: {exc}"
            stats.errors += 1
            if team is not None:
                team.leave(job.key.generation)  # from the leader: the span ends for all
            if job.member > 0:
                log.warning("%s; leaving its team", error)
                return None
            failed = Result(job.key, settings.name, error=error, start=job.start, stop=job.stop)
            return _deliver(link, settings, stop, failed, stats)
        ga = _GA(params, spec_layout, state)
        if isinstance(team, Team) and not team.leader:
            _follow(team, job, ga, stop, stats)
            return None
        return _lead(link, settings, stop, job, evaluator, stats, ga, team)
    finally:
        if team is not None:
            team.close()


def _join_team(
    session: zenoh.Session, inbox: Inbox, job: Job, evaluator: Evaluator
) -> Team | SharedTeam | None:
    """This worker's part in the span's team; None without a team or if zenoh refused the
    publishers or the shared file could not be made (a leader then evolves alone, its
    members leave after MEMBER_WAIT_S). A shared team's members all run on one machine, so
    where it is not `shared.supported` they all fall back to a zenoh team alike."""
    if not job.team:
        return None
    try:
        if job.shared and shared.supported():
            return SharedTeam.join(job, evaluator)
        return Team(session, inbox, job, evaluator)
    except (zenoh.ZError, OSError) as exc:
        log.warning("cannot join the team of %s: %s", job.key.label(), exc)
        return None


@dataclass(frozen=True)
class _GA:
    """What a span's `tell` and `ask` need: the run's GA parameters, its genome layout and
    the state before the span's first `tell`."""

    params: GAParams
    layout: Layout
    state: GAState


def _lead(
    link: _Link,
    settings: WorkerSettings,
    stop: threading.Event,
    job: Job,
    evaluator: Evaluator,
    stats: WorkerStats,
    ga: _GA,
    team: Team | SharedTeam | None,
) -> Job | None:
    """The span loop of its only worker or its team's leader: evaluate, send, tell, ask."""
    config, state = job.config, ga.state
    in_flight: deque[tuple[JobKey, zenoh.Handler[zenoh.Reply]]] = deque()

    def send(batch: list[Result]) -> None:
        payload = encode_span_results(batch)
        in_flight.append((batch[0].key, link.get(KEY_JOB_RESULT, payload)))

    batch: list[Result] = []
    sent_at = time.monotonic()
    current = replace(
        job, span=1, state=None, more=False, team=(), member=0, team_id="", shared=False
    )
    generation = job.key.generation
    finished = False
    try:
        for offset in range(job.span):
            digest = genome_digest(current.genomes)
            if team is None:
                result = _evaluate(current, settings.name, evaluator, stats)
            else:
                result = _team_evaluate(team, current, digest, settings.name, stats)
            fitness = result.fitness
            if result.error is not None or fitness is None:
                if batch:  # the generations before it count (their reply is not needed: the
                    # error's own acknowledgement comes after it); the failed one is retried
                    send(batch)
                return _deliver(link, settings, stop, result, stats)
            batch.append(replace(result, digest=digest))
            last = stop.is_set() or offset + 1 == job.span
            if last or len(batch) == SPAN_BATCH_MAX or time.monotonic() - sent_at >= SPAN_SEND_S:
                send(batch)
                batch, sent_at = [], time.monotonic()
                if not _span_acks(in_flight, keep=SPAN_WINDOW):
                    return None
            if last:
                finished = offset + 1 == job.span
                break
            generation = current.key.generation + 1
            try:
                state, _ = tell(current.genomes, fitness, state, ga.params)
                genomes, _ = ask(ga_rng(config.seed, generation), state, ga.params, ga.layout)
            except ValueError as exc:  # a state that did not fit: the server asks the rest
                log.warning(
                    "span of %s stops at generation %d: %s", job.key.label(), generation, exc
                )
                break
            key = current.key.model_copy(update={"generation": generation})
            current = replace(current, key=key, genomes=genomes)
        if batch:
            send(batch)
        _span_acks(in_flight, keep=0)
        return None
    finally:
        if team is not None and not finished:
            team.leave(generation)


def _team_evaluate(
    team: Team | SharedTeam, job: Job, digest: str, name: str, stats: WorkerStats
) -> Result:
    """The whole generation `job` with the team, as `_evaluate` would return it; the speed is
    that of this worker's own share."""
    try:
        out = team.generation(job.key.generation, job.genomes, digest)
        if out is None:
            raise RuntimeError("the team fell apart")  # only a member's span ends this way
    except Exception as exc:  # report it to the server instead of crashing the worker
        log.exception("evaluating %s failed", job.key.label())
        stats.errors += 1
        error = f"{type(exc).__name__}: {exc}"
        return Result(job.key, name, error=error, start=job.start, stop=job.stop)
    fitness, components, seconds, individuals = out
    steps = individuals * job.config.trials * job.config.steps
    speed = steps / seconds if seconds > 0 else None
    stats.jobs_done += 1
    stats.robot_steps_per_s = speed
    return Result(
        job.key, name, fitness, components, speed or 0.0, seconds, start=job.start, stop=job.stop
    )


def _help(team: SharedTeam, stop: threading.Event, stats: WorkerStats) -> None:
    """A shared team member's span: chunks of the generations its leader publishes."""
    config = team.job.config

    def progress(individuals: int, seconds: float) -> None:
        stats.jobs_done += 1
        if seconds > 0:
            stats.robot_steps_per_s = individuals * config.trials * config.steps / seconds

    try:
        team.follow(stop, progress)
    except Exception:  # the leader evaluates the chunk itself
        log.exception("shared team member failed in a span of %s", team.job.key.label())
        stats.errors += 1


def _follow(team: Team, job: Job, ga: _GA, stop: threading.Event, stats: WorkerStats) -> None:
    """A member's span: its slice of each generation, then tell and ask like the leader;
    nothing goes to the server. Leaves the team when stopping or on any failure (the leader
    evaluates its slice then)."""
    config, state, genomes = job.config, ga.state, job.genomes
    for offset in range(job.span):
        generation = job.key.generation + offset
        if stop.is_set():
            team.leave(generation)
            return
        try:
            out = team.generation(generation, genomes, genome_digest(genomes))
            if out is None:
                return
            fitness, _, seconds, individuals = out
            stats.jobs_done += 1
            if seconds > 0:
                stats.robot_steps_per_s = individuals * config.trials * config.steps / seconds
            if offset + 1 == job.span:
                return
            state, _ = tell(genomes, fitness, state, ga.params)
            genomes, _ = ask(ga_rng(config.seed, generation + 1), state, ga.params, ga.layout)
        except Exception:  # the leader evaluates this worker's slice instead
            log.exception("team member failed at generation %d of a span", generation)
            stats.errors += 1
            team.leave(generation)
            return


def _span_acks(in_flight: deque[tuple[JobKey, zenoh.Handler[zenoh.Reply]]], keep: int) -> bool:
    """Take the acknowledgements that have come, waiting for the oldest while more than
    `keep` are outstanding; False (and the rest abandoned) once one is refused or missing."""
    while in_flight:
        key, replies = in_flight[0]
        if len(in_flight) > keep:
            payload = _first_ok(replies, KEY_JOB_RESULT)
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
            log.warning("malformed acknowledgement for %s: %s", key.label(), exc)
            ack = None
        if ack is None or ack.key != key or not ack.accepted:
            reason = "no answer" if ack is None else ack.reason or "refused"
            log.info("span ends at %s: %s", key.label(), reason)
            in_flight.clear()
            return False
    return True


def _collect(
    link: _Link,
    settings: WorkerSettings,
    stop: threading.Event,
    stats: WorkerStats,
    ahead: _Ahead,
    in_hand: deque[Job],
) -> list[Job]:
    """The jobs the reply to `ahead` brings; a result not acknowledged is delivered again."""
    reply = link.read(ahead.pending)
    if ahead.result is None:
        if reply is None:
            return []
        try:
            prefetched = decode_next_reply(reply)
        except InvalidJobError as exc:
            _reject_job(link, settings, stop, stats, exc)
            return []
        except WireError as exc:
            log.warning("dropping malformed reply to a prefetch: %s", exc)
            return []
        return [] if isinstance(prefetched, Idle) else [prefetched]
    result = ahead.result
    if reply is not None:
        try:
            ack, job = decode_result_reply(reply)
        except InvalidJobError as exc:
            if exc.ack is not None and exc.ack.key == result.key:
                _reject_job(link, settings, stop, stats, exc)
                return []
        except WireError:
            pass
        else:
            if ack.key == result.key:
                if not ack.accepted:
                    log.info("%s dropped by the server: %s", result.key.label(), ack.reason)
                return [] if job is None else [job]
    log.info("no acknowledgement for %s; delivering it again", result.key.label())
    holding = tuple(j.key for j in in_hand)
    following = _deliver(link, settings, stop, result, stats, holding)
    return [] if following is None else [following]


def _next_job(
    link: _Link,
    settings: WorkerSettings,
    host: str,
    stop: threading.Event,
    stats: WorkerStats,
    backoff: _Backoff,
) -> Job | None:
    """One `get` on jobs/next: a job, or None (idle, no server, or a job it reported invalid)."""
    reply = link.read(link.ask(KEY_JOB_NEXT, _request(settings, host, stats)))
    if reply is None:
        stop.wait(backoff.next())
        return None
    backoff.reset()
    try:
        job = decode_next_reply(reply)
    except InvalidJobError as exc:
        _reject_job(link, settings, stop, stats, exc)
        return None
    except WireError as exc:
        log.warning("dropping malformed reply: %s", exc)
        stop.wait(backoff.next())
        return None
    return None if isinstance(job, Idle) else job


def _reject_job(
    link: _Link,
    settings: WorkerSettings,
    stop: threading.Event,
    stats: WorkerStats,
    exc: InvalidJobError,
) -> None:
    log.warning("rejecting invalid job: %s", exc)
    stats.errors += 1
    _deliver(link, settings, stop, Result(exc.key, settings.name, error=exc.reason), stats)


def _evaluate(job: Job, name: str, evaluator: Evaluator, stats: WorkerStats) -> Result:
    began = time.perf_counter()
    try:
        fitness, components = checked_evaluation(
            evaluator, job.config, job.key.generation, job.genomes
        )
    except Exception as exc:  # report it to the server instead of crashing the worker
        log.exception("evaluating %s failed", job.key.label())
        stats.errors += 1
        error = f"{type(exc).__name__}: {exc}"
        return Result(job.key, name, error=error, start=job.start, stop=job.stop)
    seconds = time.perf_counter() - began
    speed = job.robot_steps / seconds if seconds > 0 else None
    stats.jobs_done += 1
    stats.robot_steps_per_s = speed
    return Result(
        job.key, name, fitness, components, speed or 0.0, seconds, start=job.start, stop=job.stop
    )


def _deliver(
    link: _Link,
    settings: WorkerSettings,
    stop: threading.Event,
    result: Result,
    stats: WorkerStats,
    holding: tuple[JobKey, ...] = (),
) -> Job | None:
    """Send `result` until acknowledged; the next job if the server sent one with the Ack.

    Unless stopping or holding a job, the result asks for the next job (protocol 2), saving a
    round trip. Once stopping, two more tries, then the lease lapses on the server.
    """
    backoff = _Backoff(settings)
    tries_after_stop = 0
    while tries_after_stop < 2:
        want_next = not stop.is_set() and not holding
        reply = link.read(link.ask(KEY_JOB_RESULT, _asking(result, want_next, holding)))
        if reply is not None:
            try:
                ack, job = decode_result_reply(reply)
            except InvalidJobError as exc:
                if exc.ack is None or exc.ack.key != result.key:
                    log.warning("malformed acknowledgement for %s: %s", result.key.label(), exc)
                else:
                    _reject_job(link, settings, stop, stats, exc)
                    return None
            except WireError as exc:
                log.warning("malformed acknowledgement for %s: %s", result.key.label(), exc)
            else:
                if ack.key == result.key:
                    if not ack.accepted:
                        log.info("%s dropped by the server: %s", result.key.label(), ack.reason)
                    return job
        if stop.is_set():
            tries_after_stop += 1
        stop.wait(backoff.next())
    log.warning("gave up delivering %s while stopping", result.key.label())
    return None


def _first_ok(replies: zenoh.Handler[zenoh.Reply], key: str) -> bytes | None:
    """Wait for the first successful reply's payload; None on an error reply or none at all."""
    for reply in replies:
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        if reply.err is not None:
            log.warning("server error on %s: %s", key, reply.err.payload.to_bytes()[:200])
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
