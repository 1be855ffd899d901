"""The zenoh side of the server: a router session, the job and result queryables, worker leases.

Workers pull (docs/protocol.md): a `get` on KEY_JOB_NEXT is answered with one job or held for
the long-poll and answered idle; a `get` on KEY_JOB_RESULT is answered with an Ack. A job is
leased to one worker with a deadline derived from its robot-steps and the worker's measured
speed; the lease ends early when the worker's liveliness token vanishes. Only the result of the
current lease holder counts: a late or duplicate result is acknowledged and dropped.

All zenoh callbacks only put into a queue; one dispatcher thread does every zenoh reply and
every JobSource call, so the source needs no locking of its own against the dispatcher. The
thread blocks on that one queue for everything (requests, results, liveliness, `notify` when
new jobs exist) with a timeout of the next deadline (a lease, a long-poll, a gone worker's
expiry): nothing is polled. Once the queue is empty (or `FLUSH_EVERY_S` after the last flush,
should messages never stop) it calls `JobSource.flush`, so slow bookkeeping (writing a
finished generation) runs after the next generation's jobs are sent; the source may put it
off (told generations are written together, `WRITE_AFTER_S`) and say when to call again.

Spans: a generation that one worker evaluates in less than `span_below_s` costs less than
the round trip through this server that parallel slices would add to it (docs/protocol.md,
"Throughput"). Such a generation is cut into one job, and its worker gets it as a span: it
evolves about `span_s` of generations itself (ask and tell are pure functions of the GA state
and the seed), sending each one's result as it goes, while this server records them. Each
accepted result moves the lease to the next generation, so a span fails over like any job.

Teams (protocol 7): a span whose generations take a worker more than two `team_slice_s` is
split with idle workers, up to one per `team_slice_s` of a generation. They get the same span
as members (`Job.team`): each evaluates its slice of every generation, the members exchange
fitness among themselves (`worker.team`) and only the leader holds the lease and sends
results. Idle means waiting on a held request, or between requests (invited: the span goes
out with its next request, within `INVITE_S`): a worker whose span just ended asks again a
moment after the one that gets the next span.

Shared teams (protocol 8): idle workers on the span worker's own machine (`JobRequest.machine`:
host, boot and namespaces) split the span in shared memory instead (`worker.shared`), up to one
per `shared_slice_s` of a generation: without messages between them, a second core pays from a
few milliseconds a generation. A span goes to a shared team whenever one can be at least as
large as the zenoh team it would get.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np
import zenoh

from schemas.run import RunConfig
from schemas.security import ZenohRouterAuth
from schemas.wire import (
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    KEY_WORKERS,
    PROTOCOL,
    TEAM_MAX,
    Ack,
    Idle,
    Job,
    JobKey,
    Result,
    WireError,
    WorkerStatus,
    check_worker_name,
    decode_request,
    decode_results,
    encode_job,
    encode_message,
    genome_digest,
)
from server.jobs import JobKey as QueueKey
from server.jobs import JobQueue, JobResult
from server.logs import ContextAdapter, context

log = logging.getLogger(__name__)

FLUSH_EVERY_S = 0.5
"""The longest a busy dispatcher puts off `JobSource.flush` (writing told generations)."""
WRITE_AFTER_S = 0.1
"""How long told generations wait to be written together (`QueueSource.flush`): a span tells
hundreds a second, and a transaction per generation cost the server more than the rows in
it. A crash loses at most these, which a restart recomputes bit for bit."""
INVITE_S = 0.25
"""How long a team's place waits for a worker that was between requests (worker.team: the
leader evaluates the slice itself after LEADER_WAIT_S)."""


def _job_log(key: JobKey, worker: str) -> ContextAdapter:
    """`log` carrying the job's run, job (`run/generation/index`) and worker ids."""
    job = f"{key.run_id}/{key.generation}/{key.index}"
    return context(log, run=key.run_id, job=job, worker=worker)


class JobSource(Protocol):
    """What the dispatcher needs from a job queue; every call comes from the dispatcher thread."""

    def lease(self, worker: str) -> Job | None:
        """The next job for `worker` (now leased to it), or None if there is none."""

    def complete(self, result: Result) -> bool:
        """Store a successful result once; False if it was a duplicate or its run is over."""

    def fail(self, key: JobKey, error: str) -> None:
        """The worker reported an error: retry the job or, past the attempt limit, fail the run."""

    def release(self, key: JobKey) -> None:
        """The lease is over without a result (worker gone or late): the job is pending again."""

    def flush(self) -> float | None:
        """Do deferred work now that every reply is out (called when no message is waiting);
        if it raises, it is called again within a second. Returns in how many seconds to call
        it again for work it put off (None: none waits), so the source keeps its own clock."""


@runtime_checkable
class SpanSource(JobSource, Protocol):
    """A JobSource whose generations can be evolved by one worker (spans, protocol 5)."""

    def span(self, job: Job, worker: str, generations: int) -> Job:
        """`job` (a whole generation, leased to `worker`) as a span of up to `generations`,
        with the GA state; unchanged if it cannot be one."""

    def continues(self, key: JobKey, worker: str) -> bool:
        """Whether the generation after job `key` is now leased to `worker` (its span goes
        on after `complete`)."""

    def digest(self, key: JobKey) -> str | None:
        """`genome_digest` of job `key`'s genomes as the server asked them (None once its
        generation is no longer in flight)."""


@dataclass(frozen=True)
class DispatchSettings:
    """Zenoh endpoints and lease policy; the defaults serve a lab network."""

    listen: tuple[str, ...] = ("tcp/0.0.0.0:7447",)
    connect: tuple[str, ...] = ()
    """Optional routers to join (a lab's zenohd); empty means this process is the router."""
    multicast_scouting: bool = False
    long_poll_s: float = 1.0
    """How long a job request is held before the server answers idle."""
    lease_min_s: float = 10.0
    lease_factor: float = 10.0
    """lease = max(lease_min_s, lease_factor x robot-steps / worker robot-steps/s)."""
    lease_unknown_s: float = 120.0
    """Lease for a worker with no measured speed yet (its first job compiles the kernels)."""
    gone_keep_s: float = 600.0
    """How long a departed worker stays listed as gone."""
    jobs_per_worker: int = 1
    """A generation is cut into this many jobs per live worker (see `Dispatcher.job_size`)."""
    span_below_s: float = 0.1
    """A generation a worker evaluates faster than this runs in spans (0: never). Alone, a
    span's worker beat parallel slices below 10-20 ms a generation on a 2-core machine; split
    in a team it beat them at 15-30 ms and was about as fast at 65-130 ms (bench/dispatch.py
    --sweep)."""
    span_s: float = 5.0
    """A span covers about this much evaluation time, then its worker asks again (so other
    runs and newly joined workers get their turn)."""
    team_slice_s: float = 0.005
    """A span is split among idle workers, each evaluating at least this much of a
    generation (0: never): on a shared 2-core machine the exchange costs a generation 1-2 ms,
    and one worker alone was faster below about 10 ms a generation (bench/dispatch.py)."""
    shared_slice_s: float = 0.001
    """A span is split among idle workers of its worker's machine, each evaluating at least
    this much of a generation, in shared memory (0: never)."""
    auth: ZenohRouterAuth = field(default_factory=ZenohRouterAuth)
    """usrpwd dictionary, TLS certificate and message-size limit of the router (security.md)."""

    def __post_init__(self) -> None:
        if not self.listen and not self.connect:
            raise ValueError("a dispatcher needs at least one listen or connect endpoint")
        for name in ("long_poll_s", "lease_min_s", "lease_factor", "lease_unknown_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.gone_keep_s < 0:
            raise ValueError(f"gone_keep_s must be >= 0, got {self.gone_keep_s}")
        if self.jobs_per_worker < 1:
            raise ValueError(f"jobs_per_worker must be >= 1, got {self.jobs_per_worker}")
        if self.span_below_s < 0:
            raise ValueError(f"span_below_s must be >= 0, got {self.span_below_s}")
        if not self.span_s > 0:
            raise ValueError(f"span_s must be > 0, got {self.span_s}")
        for name in ("team_slice_s", "shared_slice_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    def lease_seconds(self, robot_steps: int, speed: float | None) -> float:
        """The lease of a job of `robot_steps` for a worker running `speed` robot-steps/s."""
        if not speed:
            return self.lease_unknown_s
        return max(self.lease_min_s, self.lease_factor * robot_steps / speed)

    def span_generations(self, config: RunConfig, speed: float | None) -> int:
        """Generations of `config` a worker of `speed` robot-steps/s evolves in one span
        (1: no span, the generation is cut into parallel slices)."""
        if not speed:
            return 1
        seconds = config.population * config.trials * config.steps / speed
        if seconds >= self.span_below_s:
            return 1
        return max(1, int(self.span_s / seconds))

    def team_size(self, config: RunConfig, speed: float | None, shared: bool = False) -> int:
        """Workers that should split a span's generations of `config` (1: no team), in
        shared memory or over zenoh."""
        slice_s = self.shared_slice_s if shared else self.team_slice_s
        if not speed or not slice_s:
            return 1
        seconds = config.population * config.trials * config.steps / speed
        return max(1, min(int(seconds / slice_s), config.population, TEAM_MAX))

    def zenoh_config(self) -> zenoh.Config:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"router"')
        conf.insert_json5("listen/endpoints", _json_list(self.listen))
        conf.insert_json5("connect/endpoints", _json_list(self.connect))
        conf.insert_json5(
            "scouting/multicast/enabled", "true" if self.multicast_scouting else "false"
        )
        # zenoh's shared memory (on by default) gives every local peer that sends more than
        # 3 KiB a 16 MiB pool, which the router maps: 64 local robots cost it 1 GiB of RSS
        conf.insert_json5("transport/shared_memory/enabled", "false")
        for key, value in self.auth.entries():
            conf.insert_json5(key, value)
        return conf


def _json_list(items: tuple[str, ...]) -> str:
    return "[" + ",".join(f'"{item}"' for item in items) + "]"


@dataclass
class _Lease:
    key: JobKey
    worker: str
    deadline: float
    robot_steps: int
    start: int
    stop: int
    span_left: int = 0
    """Generations of a span after this one."""
    continued: bool = False
    """Leased by a span going on: the worker asked these genomes itself (digest required)."""
    seq: int = 0
    """The worker's request whose reply carried it (protocol 9; 0: unnumbered)."""


@dataclass
class _WorkerRecord:
    name: str
    host: str = ""
    machine: str = ""
    """What the worker shares memory with (protocol 8): equal ones may form shared teams."""
    state: str = "idle"
    jobs_done: int = 0
    speed: float | None = None
    last_seen: float = field(default_factory=time.time)
    gone_at: float | None = None
    """Monotonic time the token vanished (None while alive)."""
    protocol: int | None = None
    """Protocol its last request spoke (None before any request)."""
    spans: bool = True
    """False once it evaluated genomes other than the server asked: its GA differs."""
    team: str | None = None
    """The team it was sent into as a member (until it asks again)."""
    seq: int = 0
    """The highest request number seen from it (protocol 9)."""

    @property
    def serving(self) -> bool:
        """Alive and not known to speak another protocol: it can take jobs."""
        return self.gone_at is None and self.protocol in (None, PROTOCOL)

    def status(self) -> WorkerStatus:
        state = "gone" if self.gone_at is not None else self.state
        return WorkerStatus(
            name=self.name,
            host=self.host,
            state="busy" if state == "busy" else "gone" if state == "gone" else "idle",
            jobs_done=self.jobs_done,
            robot_steps_per_s=self.speed,
            last_seen=self.last_seen,
        )


@dataclass
class _Held:
    query: zenoh.Query
    worker: str
    until: float
    seq: int = 0


_WAKE = object()


class Dispatcher:
    """A running dispatcher: the router session and its thread. Close it exactly once."""

    def __init__(
        self,
        settings: DispatchSettings,
        source: JobSource,
        *,
        session: zenoh.Session | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """Serve `source`; on `session` if given (the caller closes it), else on its own."""
        self.settings = settings
        self._source = source
        self._spans = source if isinstance(source, SpanSource) else None
        """The source again if it can serve spans (checked once: a protocol check is slow)."""
        self._clock = clock
        self._inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._leases: dict[JobKey, _Lease] = {}
        self._held: list[_Held] = []
        self._other_protocol: list[_Held] = []
        """Requests of workers speaking another protocol: answered idle at their long-poll's
        end, never served, so an old worker asks about once a second instead of spinning."""
        self._flush_at: float | None = None
        self._flushed_at = clock()
        self._workers: dict[str, _WorkerRecord] = {}
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self.jobs_served = 0
        self.results_accepted = 0
        self.results_dropped = 0
        self.prefetches = 0
        """Requests of workers already holding a job (protocol 3 prefetches)."""
        self.pipelined = 0
        """Requests and results of workers with a job in flight to them (protocol 9)."""
        self.spans_served = 0
        """Jobs sent as spans (protocol 5)."""
        self.teams_served = 0
        """Spans split with other workers (protocol 7)."""
        self.shared_teams_served = 0
        """Of those, split in shared memory (protocol 8)."""
        self._invites: dict[str, tuple[Job, float]] = {}
        """Team places for workers that were between requests, with their expiry."""
        self.malformed = 0
        self._owns_session = session is None
        self._session = zenoh.open(settings.zenoh_config()) if session is None else session
        try:
            self._next = self._session.declare_queryable(
                KEY_JOB_NEXT, lambda q: self._inbox.put(("next", q))
            )
            self._result = self._session.declare_queryable(
                KEY_JOB_RESULT, lambda q: self._inbox.put(("result", q))
            )
            self._alive = self._session.liveliness().declare_subscriber(
                KEY_WORKERS, lambda s: self._inbox.put(("alive", s)), history=True
            )
        except BaseException:
            if self._owns_session:
                self._session.close()  # type: ignore[no-untyped-call]
            raise
        self._thread = threading.Thread(target=self._run, name="dispatcher", daemon=True)
        self._thread.start()

    def notify(self) -> None:
        """New jobs may be leasable: answer held requests now instead of at the next poll."""
        self._inbox.put(_WAKE)

    def job_size(self, config: RunConfig, generation: int, *, local: int = 0) -> int:
        """Individuals per job of `config`'s `generation` (a `JobSizer` for the job queue):
        `jobs_per_worker` jobs per live worker (of this protocol) and per `local` evaluator
        leasing from the same queue (in-process executor threads), never smaller than the
        run's `job_size`, which also applies while none is known. Each message and each
        `evaluate` call has a fixed cost: fewer, larger jobs are cheaper; more of them balance
        unequal workers.

        The whole generation is one job when it will be a span, whoever leases it: it is not
        the run's last, and every live worker may span (it never sent a wrong digest) and has
        a speed under the span threshold. A whole generation leased to a worker that gets no
        span (or as a prefetch, never a span) would keep the others idle. So one slow worker
        means slices for every run near the threshold."""
        if local < 0:
            raise ValueError(f"local must be >= 0, got {local}")
        with self._lock:
            speeds = [w.speed if w.spans else None for w in self._workers.values() if w.serving]
        live = local + len(speeds)
        if live == 0:
            return config.job_size
        if (
            local == 0
            and generation + 1 < config.generations
            and all(speeds)
            and self.settings.span_generations(config, min(s for s in speeds if s)) > 1
        ):
            return config.population
        jobs = live * self.settings.jobs_per_worker
        return max(config.job_size, -(-config.population // jobs))

    def workers(self) -> list[WorkerStatus]:
        """Every known worker, gone ones included until `gone_keep_s` after they left."""
        with self._lock:
            return [w.status() for w in sorted(self._workers.values(), key=lambda w: w.name)]

    def close(self) -> None:
        """Stop the thread, answer held requests idle, undeclare; close the session if owned."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        self._inbox.put(_WAKE)
        self._thread.join(timeout=10.0)
        for held in self._held + self._other_protocol:
            self._answer_idle(held, "server stopping")
        self._held.clear()
        self._other_protocol.clear()
        for entity in (self._next, self._result, self._alive):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()  # type: ignore[no-untyped-call]
        if self._owns_session:
            self._session.close()  # type: ignore[no-untyped-call]

    def __enter__(self) -> Dispatcher:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # -- the dispatcher thread ---------------------------------------------------------------

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                event = self._inbox.get(timeout=self._wait_time())
            except queue.Empty:
                event = _WAKE
            while True:  # everything already waiting, then the deferred work
                if self._stopping.is_set():
                    self._finish(event)
                    return
                self._step(event)
                if self._clock() - self._flushed_at >= FLUSH_EVERY_S:
                    break  # busy without a pause: write now, then go on
                try:
                    event = self._inbox.get_nowait()
                except queue.Empty:
                    break
            self._flush_at = None
            self._flushed_at = self._clock()
            try:
                delay = self._source.flush()
                self._flush_at = None if delay is None else self._clock() + delay
            except Exception:  # e.g. the database is down: retried within a second
                log.exception("deferred job-source work failed; retrying later")
                self._flush_at = self._clock() + 1.0

    def _step(self, event: Any) -> None:
        try:
            self._handle(event)
            self._serve_held()
            self._expire()
        except Exception:  # a failing source must not stop the dispatcher
            log.exception("dispatcher step failed; continuing")

    def _finish(self, event: Any) -> None:
        if isinstance(event, tuple) and isinstance(event[1], zenoh.Query):
            with event[1] as query:
                query.reply_err(b"server stopping")

    def _wait_time(self) -> float | None:
        """Until the next deadline: a lease, a held request's long-poll, a gone worker's
        expiry from the table; None (block until a message) when there is none."""
        deadlines = [lease.deadline for lease in self._leases.values()]
        deadlines += [held.until for held in self._held + self._other_protocol]
        if self._flush_at is not None:
            deadlines.append(self._flush_at)
        with self._lock:
            deadlines += [
                w.gone_at + self.settings.gone_keep_s
                for w in self._workers.values()
                if w.gone_at is not None
            ]
        if not deadlines:
            return None
        return max(min(deadlines) - self._clock(), 0.0)

    def _handle(self, event: Any) -> None:
        if event is _WAKE:
            return
        kind, item = event
        if kind == "next":
            self._on_next(item)
        elif kind == "result":
            with item as query:
                self._on_result(query)
        else:
            self._on_alive(item)

    def _on_next(self, query: zenoh.Query) -> None:
        try:
            request = decode_request(_payload(query))
        except WireError as exc:
            self._reject(query, exc)
            return
        record = self._touch(request.worker, request.host)
        if request.robot_steps_per_s:
            record.speed = request.robot_steps_per_s
        self._release_lost(request)
        prefetch = self._holds(request, record)
        with self._lock:
            record.protocol, record.machine = request.protocol, request.machine
            if not prefetch:
                record.team, record.state = None, "idle"
        until = self._clock() + self.settings.long_poll_s
        held = _Held(query, request.worker, until, request.seq)
        place = self._invited(request.worker, prefetch)
        if place is not None:
            with query:
                self._join(query, KEY_JOB_NEXT, held.worker, place)
        elif request.protocol != PROTOCOL:
            self._other_protocol.append(held)
        elif prefetch:  # a job now or idle now, never held
            self.prefetches += 1
            if not (self._may_prefetch(request.worker) and self._try_serve(held, prefetch=True)):
                self._answer_idle(held, "no job to prefetch")
        elif not self._try_serve(held):
            self._held.append(held)

    def _release_lost(self, asks: _Asks) -> None:
        """The worker asks for work while leasing jobs it neither holds nor awaits: the replies
        that carried them got lost; put the jobs back."""
        for key in [
            k
            for k, lease in self._leases.items()
            if lease.worker == asks.worker and k not in asks.holding and not _unread(lease, asks)
        ]:
            _job_log(key, asks.worker).warning(
                "%s asked for work while leasing %s; releasing it", asks.worker, key.label()
            )
            del self._leases[key]
            self._source.release(key)

    def _holds(self, asks: _Asks, record: _WorkerRecord) -> bool:
        """Whether the worker has a job in hand or may have one in flight to it (counted in
        `pipelined`): a reply it had not read carried one, or it awaits a request not seen
        here yet (overtaken by this one), whose reply may carry one. Then it asks for a job
        ahead, as a prefetch does: never held, never a span nor a team place. Notes the
        request's number as seen."""
        unseen = bool(asks.awaiting) and asks.awaiting[-1] > record.seq
        record.seq = max(record.seq, asks.seq)
        if unseen or any(
            lease.worker == asks.worker and _unread(lease, asks) for lease in self._leases.values()
        ):
            self.pipelined += 1
            return True
        return bool(asks.holding)

    def _may_prefetch(self, worker: str) -> bool:
        """A second job for a busy worker only while no other live worker is without one: a
        prefetch must not take the job an idle worker is about to ask for."""
        busy = {lease.worker for lease in self._leases.values()}
        with self._lock:
            return all(
                w.name in busy or w.name == worker for w in self._workers.values() if w.serving
            )

    def _try_serve(self, held: _Held, *, prefetch: bool = False) -> bool:
        job = self._source.lease(held.worker)
        if job is None:
            return False
        with held.query as query:
            self._send(query, KEY_JOB_NEXT, job, held.worker, None, held.seq, may_span=not prefetch)
        return True

    def _spanned(self, job: Job, worker: str) -> Job:
        """`job` as a span if its generation is quick enough for one worker, which holds no
        other job and has never evaluated other genomes than the server asked."""
        source, record = self._spans, self._workers[worker]
        if (
            source is None
            or not record.spans
            or (job.start, job.stop) != (0, job.config.population)
            or any(lease.worker == worker for lease in self._leases.values())
        ):
            return job
        generations = self.settings.span_generations(job.config, record.speed)
        return job if generations == 1 else source.span(job, worker, generations)

    def _send(
        self,
        query: zenoh.Query,
        key: str,
        job: Job,
        worker: str,
        ack: Ack | None,
        seq: int,
        *,
        may_span: bool = True,
    ) -> None:
        """Reply `job` (with `ack` if it answers a result, to the worker's request `seq`) and
        record its lease; a job for a worker holding no other (`may_span`) may go out as a
        span."""
        record = self._workers[worker]
        if may_span:
            job = self._spanned(job, worker)
        if job.span > 1:
            job = self._teamed(job, worker)
        lease_s = self.settings.lease_seconds(job.robot_steps, record.speed)
        # A prefetch gets a job only while every other live worker holds one: otherwise it
        # would come back idle, so tell the worker not to send it. A span is never prefetched
        # behind: its worker is busy for the whole span.
        more = job.more and job.span == 1 and self._may_prefetch(worker)
        try:
            query.reply(key, encode_job(job.leased(lease_s, more), ack))
        except zenoh.ZError:
            _job_log(job.key, worker).warning(
                "could not send %s to %s; releasing it", job.key.label(), worker
            )
            self._source.release(job.key)
            for name in job.team[1:]:  # members already answered leave after MEMBER_WAIT_S
                self._uninvite(name, job.team_id)
            return
        deadline = self._clock() + lease_s
        self._leases[job.key] = _Lease(
            job.key, worker, deadline, job.robot_steps, job.start, job.stop, job.span - 1, seq=seq
        )
        if job.span > 1:
            self.spans_served += 1
            _job_log(job.key, worker).info(
                "leased %s to %s as a span of %d generations%s",
                job.key.label(),
                worker,
                job.span,
                f" {'in shared memory ' if job.shared else ''}with {', '.join(job.team[1:])}"
                if job.team
                else "",
            )
        elif log.isEnabledFor(logging.DEBUG):  # every job: not even the adapter otherwise
            _job_log(job.key, worker).debug(
                "leased %s to %s for %.0f s", job.key.label(), worker, lease_s
            )
        with self._lock:
            record.state = "busy"
        self.jobs_served += 1

    def _teamed(self, job: Job, worker: str) -> Job:
        """The span `job` of `worker` split with idle workers if its generations are long
        enough (`team_size`), in shared memory if enough share its machine: the held ones get
        their place now, the others are invited."""
        machine, speed = self._workers[worker].machine, self._workers[worker].speed
        size = self.settings.team_size(job.config, speed)
        local_size = self.settings.team_size(job.config, speed, shared=True) if machine else 1
        if max(size, local_size) < 2:
            return job
        leasing = {lease.worker for lease in self._leases.values()}
        with self._lock:
            free = {
                name
                for name, record in self._workers.items()
                if record.serving
                and record.spans
                and record.speed  # it has evaluated: its kernels are compiled
                and record.team is None
                and name != worker
                and name not in leasing
            }
        held = [h for h in self._held if h.worker in free]
        names = list(dict.fromkeys(h.worker for h in held))
        names += sorted(free - set(names))
        with self._lock:
            local = [name for name in names if self._workers[name].machine == machine]
        helpers = min(local_size - 1, len(local))
        shared = helpers >= 1 and helpers >= min(size - 1, len(names))
        names = local[: local_size - 1] if shared else names[: size - 1]
        if not names:
            return job
        team, team_id = (worker, *names), secrets.token_hex(8)
        expires = self._clock() + INVITE_S
        for member, name in enumerate(names, start=1):
            place = replace(
                job, team=team, member=member, team_id=team_id, more=False, shared=shared
            )
            with self._lock:
                self._workers[name].team = team_id
            request = next((h for h in self._held if h.worker == name), None)
            if request is None:
                self._invites[name] = (place, expires)
            else:
                self._held.remove(request)
                with request.query as query:
                    self._join(query, KEY_JOB_NEXT, name, place)
        self.teams_served += 1
        self.shared_teams_served += shared
        return replace(job, team=team, member=0, team_id=team_id, shared=shared)

    def _invited(self, worker: str, holds: bool) -> Job | None:
        """The team place `worker` was invited to, if still open and it `holds` no job."""
        invite = self._invites.pop(worker, None)
        if invite is None:
            return None
        if invite[1] <= self._clock() or holds:
            self._uninvite(worker, invite[0].team_id)
            return None
        return invite[0]

    def _uninvite(self, worker: str, team_id: str) -> None:
        """`worker` will not join team `team_id` (its leader evaluates the slice)."""
        self._invites.pop(worker, None)
        with self._lock:
            record = self._workers.get(worker)
            if record is not None and record.team == team_id:
                record.team = None

    def _join(
        self, query: zenoh.Query, key: str, worker: str, place: Job, ack: Ack | None = None
    ) -> None:
        """Answer a member's request with its place in a team (it holds no lease)."""
        try:
            query.reply(key, encode_job(place, ack))
        except zenoh.ZError:  # the leader evaluates its slice after LEADER_WAIT_S
            _job_log(place.key, worker).warning("could not send %s its place in a team", worker)
            return
        with self._lock:
            record = self._workers[worker]
            record.team, record.state = place.team_id, "busy"
        _job_log(place.key, worker).debug("%s joins the team of %s", worker, place.key.label())

    def _serve_held(self) -> None:
        """Lease to held requests in arrival order; answer idle those past their long-poll."""
        now = self._clock()
        waiting: list[_Held] = []
        exhausted = False
        while self._held:  # popped one by one: a team may take later ones meanwhile
            held = self._held.pop(0)
            if not exhausted and self._try_serve(held):
                continue
            exhausted = True
            if held.until <= now:
                self._answer_idle(held, "no job")
            else:
                waiting.append(held)
        self._held = waiting
        for held in [h for h in self._other_protocol if h.until <= now]:
            self._answer_idle(held, f"server speaks protocol {PROTOCOL}")
        self._other_protocol = [h for h in self._other_protocol if h.until > now]

    def _answer_idle(self, held: _Held, reason: str) -> None:
        with contextlib.suppress(zenoh.ZError), held.query as query:
            query.reply(KEY_JOB_NEXT, encode_message(Idle(reason=reason)))

    def _on_result(self, query: zenoh.Query) -> None:
        """A result, or consecutive generations of a span (taken in order until one is
        refused); one acknowledgement, under the first one's key."""
        try:
            results = decode_results(_payload(query))
        except WireError as exc:
            self._reject(query, exc)
            return
        result = results[0]
        record = self._touch(result.worker, None)
        holds = self._holds(result, record)
        for each in results:
            ack = self._take(each, record)
            if not ack.accepted:
                break
        if ack.key != result.key:
            ack = ack.model_copy(update={"key": result.key})
        if result.want_next:
            # Pipelined request (protocol 2): the next job rides on the acknowledgement.
            # Requests already held waited longer: they are served first (a span among them
            # may invite this worker into its team). A worker with a job in hand or in flight
            # gets one as a prefetch would.
            self._serve_held()
            place = self._invited(result.worker, holds)
            if place is not None:
                self._join(query, KEY_JOB_RESULT, result.worker, place, ack)
                return
            self._release_lost(result)
            job = (
                None
                if self._held or (holds and not self._may_prefetch(result.worker))
                else self._source.lease(result.worker)
            )
            if job is not None:
                self._send(
                    query, KEY_JOB_RESULT, job, result.worker, ack, result.seq, may_span=not holds
                )
                return
        query.reply(KEY_JOB_RESULT, encode_message(ack))

    def _take(self, result: Result, record: _WorkerRecord) -> Ack:
        """Settle one result if its worker holds the lease (a span's lease then moves on)."""
        lease = self._leases.get(result.key)
        if lease is None or lease.worker != result.worker or _other_slice(result, lease):
            self.results_dropped += 1
            _job_log(result.key, result.worker).debug(
                "dropped a late or duplicate result of %s from %s",
                result.key.label(),
                result.worker,
            )
            return Ack(key=result.key, accepted=False, reason="no lease held: late or duplicate")
        del self._leases[result.key]
        ack = self._settle(result, lease)
        if ack.accepted and result.error is None and lease.span_left > 0:
            self._go_on(result.key, lease)
        still = any(other.worker == result.worker for other in self._leases.values())
        with self._lock:
            record.state = "busy" if still else "idle"
            if result.robot_steps_per_s:
                record.speed = result.robot_steps_per_s
        return ack

    def _go_on(self, key: JobKey, lease: _Lease) -> None:
        """The span's next generation is leased to the same worker (if the source went on)."""
        if self._spans is None or not self._spans.continues(key, lease.worker):
            return
        following = key.model_copy(update={"generation": key.generation + 1})
        speed = self._workers[lease.worker].speed
        deadline = self._clock() + self.settings.lease_seconds(lease.robot_steps, speed)
        self._leases[following] = replace(
            lease, key=following, deadline=deadline, span_left=lease.span_left - 1, continued=True
        )

    def _settle(self, result: Result, lease: _Lease) -> Ack:
        if result.error is None and lease.continued:
            error = self._check_digest(result)
            if error is not None:
                result = replace(result, fitness=None, components=None, error=error)
        if result.error is not None:
            _job_log(result.key, result.worker).warning(
                "%s failed %s: %s", result.worker, result.key.label(), result.error
            )
            self._source.fail(result.key, f"{result.worker}: {result.error}")
            return Ack(key=result.key, accepted=True, reason="error recorded")
        accepted = self._source.complete(result)
        if accepted:
            self.results_accepted += 1
            with self._lock:
                self._workers[result.worker].jobs_done += 1
            if log.isEnabledFor(logging.DEBUG):
                _job_log(result.key, result.worker).debug(
                    "%s completed %s", result.worker, result.key.label()
                )
        else:
            self.results_dropped += 1
            _job_log(result.key, result.worker).debug(
                "dropped a duplicate result of %s from %s", result.key.label(), result.worker
            )
        return Ack(key=result.key, accepted=accepted, reason="" if accepted else "duplicate")

    def _check_digest(self, result: Result) -> str | None:
        """Why a span's generation cannot count (None if it can): the worker must have
        evaluated the genomes the server asked. A worker that did not runs another GA (another
        version?): it gets no more spans, only genomes asked here."""
        expected = None if self._spans is None else self._spans.digest(result.key)
        if result.digest is None:
            return "a span's result without its digest"
        if expected is None or result.digest == expected:
            return None
        with self._lock:
            self._workers[result.worker].spans = False
        _job_log(result.key, result.worker).warning(
            "%s evaluated other genomes than the server asked for %s (its GA differs: another "
            "version?); no more spans for it",
            result.worker,
            result.key.label(),
        )
        return "evaluated other genomes than the server asked (its GA differs: another version?)"

    def _on_alive(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            check_worker_name(name)
        except ValueError:
            self.malformed += 1
            log.warning("ignoring liveliness token with a bad worker name %r", name)
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self._touch(name, None)
            return
        self._invites.pop(name, None)
        with self._lock:
            record = self._workers.setdefault(name, _WorkerRecord(name))
            record.gone_at = self._clock()
            record.team = None
        context(log, worker=name).info("worker %s gone", name)
        # a request it left held must not take a job: the job would wait out a lease
        for held in [h for h in self._held if h.worker == name]:
            self._answer_idle(held, "worker gone")
        self._held = [h for h in self._held if h.worker != name]
        for key in [k for k, lease in self._leases.items() if lease.worker == name]:
            _job_log(key, name).warning(
                "worker %s vanished holding %s; releasing it", name, key.label()
            )
            del self._leases[key]
            self._source.release(key)

    def _touch(self, name: str, host: str | None) -> _WorkerRecord:
        with self._lock:
            record = self._workers.get(name)
            if record is None or record.gone_at is not None:
                context(log, worker=name).info("worker %s joined (host %s)", name, host or "?")
            if record is None:
                record = self._workers[name] = _WorkerRecord(name)
            record.last_seen = time.time()
            record.gone_at = None
            if host:
                record.host = host
            return record

    def _expire(self) -> None:
        now = self._clock()
        for name, (place, expires) in list(self._invites.items()):
            if expires <= now:
                self._uninvite(name, place.team_id)
        for key, lease in list(self._leases.items()):
            if lease.deadline <= now:
                _job_log(key, lease.worker).warning(
                    "lease of %s to %s expired; releasing it", key.label(), lease.worker
                )
                del self._leases[key]
                self._source.release(key)
                with self._lock:
                    record = self._workers.get(lease.worker)
                    if record is not None:
                        record.state = "idle"
        with self._lock:
            for name, record in list(self._workers.items()):
                if record.gone_at is not None and now - record.gone_at > self.settings.gone_keep_s:
                    del self._workers[name]

    def _reject(self, query: zenoh.Query, exc: Exception) -> None:
        self.malformed += 1
        log.warning("dropping malformed message on %s: %s", query.key_expr, exc)
        with contextlib.suppress(zenoh.ZError), query:
            query.reply_err(f"malformed: {exc}".encode())


class _Asks(Protocol):
    """What a request for a job says of its worker: a `JobRequest`, or a `Result` that wants
    the next job."""

    @property
    def worker(self) -> str: ...
    @property
    def holding(self) -> tuple[JobKey, ...]: ...
    @property
    def seq(self) -> int: ...
    @property
    def awaiting(self) -> tuple[int, ...]: ...


def _unread(lease: _Lease, asks: _Asks) -> bool:
    """Whether the reply that carried `lease` was still unread when the worker sent `asks`
    (protocol 9): it names that reply's request as awaited, or sent it after `asks` (requests
    on the two keys may arrive out of order)."""
    return lease.seq in asks.awaiting or 0 < asks.seq < lease.seq


def _other_slice(result: Result, lease: _Lease) -> bool:
    """The result is for another cut of the generation (a job leased by an earlier server life
    under the same key): late, whatever its key says."""
    return result.start is not None and (result.start, result.stop) != (lease.start, lease.stop)


def _payload(query: zenoh.Query) -> bytes:
    payload = query.payload
    if payload is None:
        raise WireError("query has no payload")
    return payload.to_bytes()


def start_dispatcher(settings: DispatchSettings, source: JobSource) -> Dispatcher:
    """Open the router session and start serving `source`; call `.close()` on shutdown."""
    return Dispatcher(settings, source)


class QueueSource:
    """The JobSource over the server's job queue (`server.jobs.JobQueue`)."""

    def __init__(self, queue: JobQueue, *, clock: Callable[[], float] = time.time) -> None:
        self._queue = queue
        self._clock = clock
        self._told_at: float | None = None
        """When `flush` first found generations unwritten (the oldest waits from then)."""

    def lease(self, worker: str) -> Job | None:
        job = self._queue.lease(worker, self._clock())
        if job is None:
            return None
        key = JobKey(run_id=job.key.run_id, generation=job.key.generation, index=job.key.index)
        genomes = np.ascontiguousarray(job.genomes, dtype=np.float64)
        return Job(key, job.start, job.stop, job.config, genomes, more=self._queue.has_pending())

    def complete(self, result: Result) -> bool:
        key = _queue_key(result.key)
        if result.fitness is None or result.components is None:
            self._queue.fail(key, f"{result.worker}: result without fitness or components")
            return False
        try:
            job_result = JobResult(result.fitness, result.components)
            return self._queue.complete(key, job_result, defer=True, now=self._clock())
        except ValueError as exc:  # wrong shapes: the worker is broken, count it as a failure
            self._queue.fail(key, f"{result.worker}: {exc}")
            return False

    def span(self, job: Job, worker: str, generations: int) -> Job:
        granted, state = self._queue.grant_span(_queue_key(job.key), worker, generations)
        if granted == 1 or state is None:
            return job
        return replace(job, span=granted, state=state.to_arrays(), more=False)

    def continues(self, key: JobKey, worker: str) -> bool:
        following = QueueKey(key.run_id, key.generation + 1, key.index)
        return self._queue.leased_to(following) == worker

    def digest(self, key: JobKey) -> str | None:
        genomes = self._queue.genomes(_queue_key(key))
        return None if genomes is None else genome_digest(genomes)

    def fail(self, key: JobKey, error: str) -> None:
        self._queue.fail(_queue_key(key), error)

    def release(self, key: JobKey) -> None:
        self._queue.release(_queue_key(key))

    def flush(self) -> float | None:
        """Write the generations told since the last write (after their successors' jobs went
        out: workers evaluate g + 1 while g is written) once they have waited `WRITE_AFTER_S`
        since the first call that found them, or at once if one finishes its run; else the
        seconds until then."""
        if not self._queue.unwritten():  # none, or written meanwhile (housekeeping, lifecycle)
            self._told_at = None
            return None
        now = self._clock()
        if self._told_at is None:
            self._told_at = now
        due = self._told_at + WRITE_AFTER_S
        if due > now and not self._queue.finishing():
            return due - now
        self._told_at = None
        self._queue.flush()
        return None


def _queue_key(key: JobKey) -> QueueKey:
    return QueueKey(key.run_id, key.generation, key.index)
