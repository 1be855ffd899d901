"""The zenoh side of the job path: a thin adapter between workers and the scheduler.

Workers pull (docs/protocol.md): a `get` on KEY_JOB_NEXT is answered with a job or held for
the long-poll and answered idle; a `get` on KEY_JOB_RESULT is answered with an Ack, or with
the worker's next job carrying it. Liveliness tokens tell the scheduler who is alive. Every
decision (which job, which lease, spans, what counts) is the scheduler's.

The zenoh callbacks only put into a queue; one thread does every reply and every scheduler
call, blocking on that queue with a timeout of the next deadline (a long-poll or a lease).
A bad message is logged, answered with an error and dropped; no message can stop the thread
(`alive` says if it stopped anyway, for `/healthz`).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from dataclasses import dataclass, field
from typing import Any

import zenoh

from schemas.security import ZenohRouterAuth
from schemas.wire import (
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    KEY_WORKERS,
    PROTOCOL,
    Ack,
    Idle,
    Job,
    JobRequest,
    Result,
    WireError,
    check_worker_name,
    decode,
    encode,
    worker_key,
)
from server.core.auth import is_loopback
from server.core.logs import context
from server.core.settings import Settings
from server.runs.scheduler import Scheduler

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DispatchSettings:
    """Zenoh endpoints of the server's router; the defaults serve a lab network."""

    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    connect: tuple[str, ...] = ()
    """Optional routers to join (a lab's zenohd); empty means this process is the router."""
    multicast_scouting: bool = False
    long_poll_s: float = 1.0
    """How long a job request is held before the server answers idle."""
    auth: ZenohRouterAuth = field(default_factory=ZenohRouterAuth)
    """usrpwd dictionary, TLS certificate and message-size limit of the router (security.md)."""

    def __post_init__(self) -> None:
        if not self.listen and not self.connect:
            raise ValueError("a dispatcher needs at least one listen or connect endpoint")
        if not self.long_poll_s > 0:
            raise ValueError(f"long_poll_s must be > 0, got {self.long_poll_s}")
        public = [e for e in self.listen if not is_loopback(endpoint_host(e))]
        if public and not self.auth.authenticates:
            raise ValueError(
                f"refusing to listen for zenoh on {public[0]} without authentication: give "
                "the server a lab's users and roles (colony lab init; docs/deployment.md) or "
                "listen on tcp/127.0.0.1:7447"
            )
        if self.connect and self.auth.roles is not None:
            raise ValueError(
                "zenoh roles are enforced by the router clients connect to: with --zenoh-connect "
                "that router is the lab's zenohd, which needs the access control itself"
            )

    @classmethod
    def from_settings(cls, settings: Settings) -> DispatchSettings:
        """ValueError if zenoh has neither a listen nor a connect endpoint."""
        return cls(
            listen=tuple(settings.zenoh_listen),
            connect=tuple(settings.zenoh_connect),
            auth=settings.zenoh_router_auth(),
        )

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


def endpoint_host(endpoint: str) -> str:
    """The host of a zenoh endpoint such as `tcp/0.0.0.0:7447` or `tls/[::1]:7448#iface=lo`."""
    address = endpoint.split("/", 1)[-1].split("#", 1)[0].split("?", 1)[0]
    return address.rsplit(":", 1)[0].strip("[]")


def _json_list(items: tuple[str, ...]) -> str:
    return "[" + ",".join(f'"{item}"' for item in items) + "]"


@dataclass
class _Held:
    query: zenoh.Query
    request: JobRequest
    until: float
    served: bool = True
    """False for a worker of another protocol: answered idle at `until`, never served."""

    @property
    def worker(self) -> str:
        return self.request.worker


_WAKE = object()


class Dispatcher:
    """A running dispatcher: the queryables, the liveliness subscriber and its thread."""

    def __init__(
        self,
        settings: DispatchSettings,
        scheduler: Scheduler,
        *,
        session: zenoh.Session | None = None,
    ) -> None:
        """Serve `scheduler`; on `session` if given (the caller closes it), else on its own."""
        self.settings = settings
        self._scheduler = scheduler
        self._clock = scheduler.now
        self._inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._held: list[_Held] = []
        self._tokens: set[str] = set()
        """Worker names whose liveliness token is declared: only they are leased jobs, and
        only they enter the scheduler's worker table (a name without one would never leave)."""
        self._stopping = threading.Event()
        self.malformed = 0
        """Messages dropped as malformed (a metric)."""
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
        scheduler.add_listener(self.notify)
        self._thread = threading.Thread(target=self._run, name="dispatcher", daemon=True)
        self._thread.start()

    def notify(self) -> None:
        """Jobs may be leasable: serve held requests now."""
        self._inbox.put(_WAKE)

    def alive(self) -> bool:
        """Whether the dispatcher thread runs (`/healthz`)."""
        return self._thread.is_alive()

    def close(self) -> None:
        """Stop the thread, answer held requests idle, undeclare; close the session if owned."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        self._scheduler.remove_listener(self.notify)
        self._inbox.put(_WAKE)
        self._thread.join(timeout=10.0)
        for held in self._held:
            self._answer_idle(held, "server stopping")
        self._held.clear()
        for entity in (self._next, self._result, self._alive):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()  # type: ignore[no-untyped-call]
        if self._owns_session:
            self._session.close()  # type: ignore[no-untyped-call]

    def __enter__(self) -> Dispatcher:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # the dispatcher thread ---------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                event = self._inbox.get(timeout=self._wait_time())
            except queue.Empty:
                event = _WAKE
            if self._stopping.is_set():
                if isinstance(event, tuple) and isinstance(event[1], zenoh.Query):
                    with contextlib.suppress(zenoh.ZError), event[1] as query:
                        query.reply_err(b"server stopping")
                return
            try:
                self._handle(event)
                self._scheduler.expire()
                self._serve_held()
            except Exception:  # one bad message or a failing call must not stop serving
                log.exception("dispatcher step failed; continuing")

    def _wait_time(self) -> float | None:
        """Until the next deadline: a held request's long-poll or a lease; None if none."""
        deadlines = [held.until for held in self._held]
        lease = self._scheduler.next_deadline()
        if lease is not None:
            deadlines.append(lease)
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
            request = decode(_payload(query), JobRequest)
            _check_sender(request.worker, query)
        except WireError as exc:
            self._reject(query, exc)
            return
        held = _Held(
            query, request, self._clock() + self.settings.long_poll_s, request.protocol == PROTOCOL
        )
        if request.worker in self._tokens:
            self._join(held)
        if not (held.served and self._try_serve(held)):
            self._held.append(held)  # a name without a token waits for it, or its long-poll

    def _join(self, held: _Held) -> None:
        request = held.request
        self._scheduler.join(
            request.worker,
            host=request.host,
            threads=request.threads,
            speed=request.robot_steps_per_s,
            serving=held.served,
        )

    def _on_result(self, query: zenoh.Query) -> None:
        try:
            result = decode(_payload(query), Result)
            _check_sender(result.worker, query)
        except WireError as exc:
            self._reject(query, exc)
            return
        if result.worker not in self._tokens:  # it holds no lease: it never had one
            ack = Ack(key=result.key, accepted=False, reason="no liveliness token: no lease held")
            query.reply(query.key_expr, encode(ack))
            return
        ack = self._scheduler.settle(result)  # it logs the error results it takes
        if result.want_next:
            self._serve_held()  # requests held waited longer: they go first
            job = None if self._held else self._scheduler.lease(result.worker)
            if job is not None:
                self._send(query, job, result.worker, ack)
                return
        query.reply(query.key_expr, encode(ack))

    def _on_alive(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            check_worker_name(name)
        except ValueError:
            self.malformed += 1
            log.warning("ignoring liveliness token with a bad worker name %r", name)
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self._tokens.add(name)
            self._scheduler.join(name, asked=False)  # a token alone: it counts once it asks
            for held in self._held:
                if held.worker == name:
                    self._join(held)
            context(log, worker=name).info("worker %s joined", name)
            self._serve_held()  # its requests held until its token came
            return
        self._tokens.discard(name)
        context(log, worker=name).info("worker %s gone", name)
        for held in [h for h in self._held if h.worker == name]:
            self._answer_idle(held, "worker gone")  # it must not take a job
        self._held = [h for h in self._held if h.worker != name]
        for key in self._scheduler.leave(name):
            context(log, worker=name).warning("worker %s vanished holding %s", name, key.label())

    def _serve_held(self) -> None:
        """Lease to held requests in arrival order; answer idle those past their long-poll."""
        now = self._clock()
        waiting: list[_Held] = []
        exhausted = False
        for held in self._held:
            servable = held.served and held.worker in self._tokens
            if servable and not exhausted and self._try_serve(held):
                continue
            # nothing for this one: for none at all unless jobs wait that its credential may
            # not take (a job it erred on)
            exhausted = exhausted or (servable and not self._scheduler.has_pending())
            if held.until <= now:
                if not held.served:
                    reason = f"server speaks protocol {PROTOCOL}"
                elif held.worker not in self._tokens:
                    reason = f"no liveliness token: declare {worker_key(held.worker)} first"
                else:
                    reason = "no job"
                self._answer_idle(held, reason)
            else:
                waiting.append(held)
        self._held = waiting

    def _try_serve(self, held: _Held) -> bool:
        """Whether `held` is answered: with a job, or an error if leasing it failed (a failing
        request must not stay held, holding up the others behind it for good)."""
        if held.worker not in self._tokens:
            return False
        try:
            job = self._scheduler.lease(held.worker)
        except Exception:
            log.exception(
                "leasing to %s failed; its request is answered with an error", held.worker
            )
            with contextlib.suppress(zenoh.ZError), held.query as query:
                query.reply_err(b"server error")
            return True
        if job is None:
            return False
        with held.query as query:
            self._send(query, job, held.worker, None)
        return True

    def _send(self, query: zenoh.Query, job: Job, worker: str, ack: Ack | None) -> None:
        """Reply `job` (with `ack` if it answers a result). If the reply cannot go, the lease
        returns when the worker asks again, leaves, or its deadline passes."""
        try:
            reply = job if ack is None else job.model_copy(update={"ack": ack})
            query.reply(query.key_expr, encode(reply))
        except zenoh.ZError:
            context(log, worker=worker).warning("could not send %s to %s", job.key.label(), worker)
            return
        if job.span > 1:
            context(log, run=job.key.run_id, worker=worker).info(
                "leased %s to %s as a span of %d generations", job.key.label(), worker, job.span
            )

    def _answer_idle(self, held: _Held, reason: str) -> None:
        with contextlib.suppress(zenoh.ZError), held.query as query:
            query.reply(query.key_expr, encode(Idle(reason=reason)))

    def _reject(self, query: zenoh.Query, exc: Exception) -> None:
        self.malformed += 1
        log.warning("dropping malformed message on %s: %s", query.key_expr, exc)
        with contextlib.suppress(zenoh.ZError), query:
            query.reply_err(f"malformed: {exc}".encode())


def _check_sender(worker: str, query: zenoh.Query) -> None:
    """WireError unless `worker` is the worker whose key the query came on: zenoh's access
    control lets only that worker's credentials use its keys (docs/security.md)."""
    key = str(query.key_expr)
    if worker != key.rsplit("/", 1)[-1]:
        raise WireError(f"worker {worker} may not send on {key}")


def _payload(query: zenoh.Query) -> bytes:
    payload = query.payload
    if payload is None:
        raise WireError("query has no payload")
    return payload.to_bytes()
