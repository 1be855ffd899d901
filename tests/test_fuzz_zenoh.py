"""Malformed payloads on every zenoh key the server, workers and agents listen to.

Real sessions on 127.0.0.1 (free ports, multicast scouting off). Each hypothesis payload is
random bytes, a frame with a random header and arrays, or a valid message with bytes flipped,
cut or inserted. The receiver must log and drop it and keep serving: right after the garbage a
valid message on the same key is answered correctly.
"""

from __future__ import annotations

import contextlib
import queue
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from evorobotics.evolution import RunLoop
from robot_agent.agent import Agent, AgentSettings
from robot_agent.driver import BasicXDriver
from robot_agent.emulator import BasicXEmulator
from robot_agent.sim_body import SimBody
from schemas.robots import (
    KEY_TRACES,
    ControllerPush,
    PushAck,
    RobotStatus,
    StuckRequest,
    TraceAck,
    TraceBatch,
    ack_key,
    alive_key,
    command_key,
    decode_message,
    decode_trace,
    encode_trace,
    replace_key,
    traces_key,
)
from schemas.robots import encode_message as encode_robot_message
from schemas.run import RunConfig
from schemas.wire import (
    ALLOWED_DTYPES,
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    MAGIC,
    NAME_PATTERN,
    Ack,
    Idle,
    Job,
    JobKey,
    JobRequest,
    Result,
    WireError,
    decode,
    decode_next_reply,
    decode_result_reply,
    encode,
    encode_frame,
    next_key,
    result_key,
)
from server.core.db import make_engine, upgrade
from server.robots.service import RobotService
from server.robots.settings import RobotSettings
from server.runs.dispatch import Dispatcher, DispatchSettings
from server.runs.policy import Policy
from server.runs.scheduler import Scheduler
from tests.helpers import (
    WAIT,
    as_worker,
    client_config,
    eventually,
    fake_evaluator,
    fake_fitness,
    free_port,
    random_controller,
    router_config,
    worker_thread,
    zenoh_client,
)

FUZZ = settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
KINDS = ["next", "job", "idle", "ack", "result", "push", "stop", "trace", "trace-ack", "stuck"]
KINDS += ["replacement", "", "\x00"]
STATUS = RobotStatus(state="running", steps=3, sha256=None, serial_ok=True)
CONFIG = RunConfig(population=6, job_size=2, generations=100_000, trials=1, steps=5)
RUN = 1
POLICY = Policy(lease_min_s=1.0, lease_max_s=2.0, lease_unknown_s=2.0)
"""Short leases: a job leased to a name garbage happened to carry returns within seconds."""
LONG_POLL_S = 4.0
GARBLER = "garbler"
"""The worker the job fuzzer's garbage comes from (its keys, its templates): a mutation that
forms a valid result claiming the impossible is a forgery, and quarantines its sender, never
`fuzzer`, who leases and settles after each payload."""


def trace(robot: str, first: int, n: int = 3) -> TraceBatch:
    return TraceBatch(
        robot=robot,
        boot=0,
        controllers=("0" * 64,),
        status=STATUS,
        steps=np.arange(first, first + n, dtype=np.int64),
        whiskers=np.zeros((n, 5), np.uint8),
        motors=np.full((n, 2), 0.25),
        controller=np.zeros(n, np.int32),
        fresh=np.zeros(n, np.bool_),
        times=np.full(n, time.time()),
        poses=np.zeros((n, 3)),
        pose_source="odometry",
    )


def _job() -> Job:
    """Job 0 of generation 0 of CONFIG, as the scheduler leases it."""
    genomes = RunLoop(CONFIG).ask()[0:2]
    key = JobKey(run_id=RUN, generation=0, index=0)
    return Job(key=key, start=0, stop=2, config=CONFIG, genomes=np.array(genomes))


def fitted(job: Job, worker: str = "fuzzer", **fields: Any) -> Result:
    """A result of `job`, as `fake_evaluator` finds it."""
    fitness, components, descriptors = fake_evaluator(job.config, job.key.generation, job.genomes)
    return Result(
        key=job.key,
        worker=worker,
        start=job.start,
        stop=job.stop,
        fitness=fitness[np.newaxis],
        components=components[np.newaxis],
        descriptors=descriptors[np.newaxis],
        **fields,
    )


def forged() -> bytes:
    """`GARBLER`'s result of `_job` claiming 1e308 for every individual, as a mutation may."""
    result = fitted(_job(), GARBLER)
    assert result.fitness is not None
    return encode(result.model_copy(update={"fitness": np.full_like(result.fitness, 1e308)}))


VALID: list[bytes] = [
    encode(JobRequest(worker=GARBLER, robot_steps_per_s=1e4)),
    encode(fitted(_job(), GARBLER)),
    encode(_job()),
    encode(Ack(key=_job().key, accepted=True)),
    encode(Idle(reason="no job")),
    encode_trace(trace("template-bot", 0)),
    encode_robot_message(
        StuckRequest(robot="template-bot", sha256=None, reason="x", step=1, nonce="0" * 32)
    ),
    encode_robot_message(TraceAck(robot="template-bot", last=5)),
    encode_robot_message(ControllerPush(push_id="p", sha256="0" * 64, document="{}")),
]

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)  # what a frame header holds (orjson: 64-bit integers)
    | st.floats()
    | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=8,
)


@st.composite
def random_frame(draw: st.DrawFn) -> bytes:
    """A well-formed EVC1 frame whose header and arrays are nonsense."""
    header: dict[str, Any] = draw(st.dictionaries(st.text(max_size=10), json_values, max_size=6))
    header["kind"] = draw(st.sampled_from(KINDS) | st.text(max_size=8))
    arrays: dict[str, np.ndarray] = {}
    for name in draw(st.lists(st.sampled_from(["genomes", "fitness", "steps", "x"]), max_size=3)):
        dtype = draw(st.sampled_from(sorted(ALLOWED_DTYPES)))
        shape = tuple(draw(st.lists(st.integers(0, 4), min_size=1, max_size=3)))
        raw = draw(st.binary(min_size=int(np.prod(shape)) * np.dtype(dtype).itemsize))
        size = int(np.prod(shape)) * np.dtype(dtype).itemsize
        arrays[name] = np.frombuffer(raw[:size], dtype=dtype).reshape(shape)
    return encode_frame(header, arrays)


@st.composite
def mutated(draw: st.DrawFn) -> bytes:
    """A valid message with a few bytes flipped, cut or inserted."""
    data = bytearray(draw(st.sampled_from(VALID)))
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, len(data)))
        action = draw(st.sampled_from(["flip", "cut", "insert"]))
        if action == "flip" and at < len(data):
            data[at] ^= draw(st.integers(1, 255))
        elif action == "cut":
            del data[at:]
        else:
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
    return bytes(data)


garbage = st.one_of(
    st.binary(max_size=300),
    st.builds(
        lambda n, rest: MAGIC + struct.pack("<I", n) + rest,
        st.integers(0, 2**32 - 1),
        st.binary(max_size=64),
    ),
    random_frame(),
    mutated(),
)


def ask(session: zenoh.Session, key: str, payload: bytes) -> zenoh.Reply:
    """The first reply; retries while the queryable's declaration propagates."""
    deadline = threading.Event()
    for _ in range(int(WAIT / 0.05)):
        replies = list(session.get(key, payload=payload, timeout=2 * LONG_POLL_S))
        if replies:
            return replies[0]
        deadline.wait(0.05)
    raise AssertionError(f"no reply on {key}")


def refused_or_valid(reply: zenoh.Reply) -> bool:
    """Garbage is answered with reply_err("malformed: ..."); a payload that happens to be a
    valid message gets an ordinary reply. Whether it was refused."""
    if reply.err is not None:
        assert reply.err.payload.to_bytes().startswith(b"malformed")
        return True
    assert reply.ok is not None
    return False


# ------------------------------------------------------------------------------ server: jobs


@contextlib.contextmanager
def job_server() -> Iterator[tuple[Dispatcher, Scheduler, zenoh.Session]]:
    """A real dispatcher over a real scheduler serving a long run, and a client session. A
    thread stands in for the run manager's writer: it takes the told generations and reports
    them written (storing nothing), else the run stops once its store lags (`store_lag_s`)."""
    port = free_port()
    scheduler = Scheduler(POLICY)
    scheduler.add(RUN, RunLoop(CONFIG), running=True)
    settings = DispatchSettings(listen=(f"tcp/127.0.0.1:{port}",), long_poll_s=LONG_POLL_S)
    stop = threading.Event()

    def store() -> None:
        while not stop.wait(0.05):
            scheduler.written(scheduler.take_told())

    writer = threading.Thread(target=store, name="fuzz-store")
    writer.start()
    try:
        with (
            Dispatcher(settings, scheduler) as disp,
            zenoh_client(port) as session,
        ):
            yield disp, scheduler, session
            assert disp.alive()
    finally:
        stop.set()
        writer.join(timeout=WAIT)


@pytest.fixture(scope="module")
def dispatcher() -> Iterator[tuple[Dispatcher, Scheduler, zenoh.Session]]:
    with job_server() as served:
        yield served


def lease(session: zenoh.Session, worker: str = "fuzzer", speed: float | None = None) -> Job:
    """A valid request, the worker's token declared: a job of the run (asking again returns
    what the worker held, for what is left of its lease)."""
    as_worker(session, worker)
    request = JobRequest(worker=worker, robot_steps_per_s=speed)
    reply = ask(session, next_key(worker), encode(request))
    assert reply.ok is not None, reply.err and reply.err.payload.to_bytes()
    job = decode_next_reply(reply.ok.payload.to_bytes())
    assert isinstance(job, Job) and job.key.run_id == RUN
    assert 0 < job.lease_s <= POLICY.lease_max_s
    return job


def settle(session: zenoh.Session, result: Result) -> tuple[Ack, Job | None]:
    reply = ask(session, result_key(result.worker), encode(result))
    assert reply.ok is not None, reply.err and reply.err.payload.to_bytes()
    ack, job = decode_result_reply(reply.ok.payload.to_bytes())
    assert ack.key == result.key
    if job is not None:
        assert job.lease_s <= POLICY.lease_max_s
    return ack, job


def of_this_protocol(key: str, reply: zenoh.Reply) -> None:
    """An ordinary reply is a message of protocol 11 for its key."""
    if reply.ok is None:
        return
    payload = reply.ok.payload.to_bytes()
    if key == next_key(GARBLER):
        assert isinstance(decode_next_reply(payload), Job | Idle)
    else:
        decode_result_reply(payload)


@FUZZ
@given(payload=garbage)
@example(payload=forged())  # quarantines its sender: the others lease on
def test_job_queryables_drop_garbage_and_keep_serving(
    dispatcher: tuple[Dispatcher, Scheduler, zenoh.Session], payload: bytes
) -> None:
    disp, scheduler, session = dispatcher
    as_worker(session, GARBLER)  # its garbage reaches the scheduler: forgeries quarantine it
    assert eventually(lambda: GARBLER in {w.name for w in scheduler.workers()}, WAIT)
    for key in (next_key(GARBLER), result_key(GARBLER)):
        before = disp.malformed
        reply = ask(session, key, payload)
        if refused_or_valid(reply):
            assert disp.malformed > before  # counted
        else:
            of_this_protocol(key, reply)
    assert "fuzzer" not in scheduler.quarantined()
    job = lease(session)
    ack, _ = settle(session, fitted(job))
    assert ack.accepted, ack.reason
    assert disp.alive()


def test_bad_worker_liveliness_names_are_dropped(
    dispatcher: tuple[Dispatcher, Scheduler, zenoh.Session],
) -> None:
    disp, scheduler, session = dispatcher
    before = disp.malformed
    bad = ["bad name", "é", "x" * 129, "a:b", "~!@%+", "a/b/c"]  # a/b/c matches no token key
    tokens = [session.liveliness().declare_token(f"evocolony/workers/{n}") for n in bad]
    good = session.liveliness().declare_token("evocolony/workers/fuzz-good")
    try:
        assert eventually(lambda: "fuzz-good" in {w.name for w in scheduler.workers()}, WAIT)
        assert eventually(lambda: disp.malformed >= before + len(bad) - 1, WAIT)
        names = {w.name for w in scheduler.workers()}
        assert not any(n in names for n in bad)
        settle(session, fitted(lease(session)))
    finally:
        for token in [*tokens, good]:
            token.undeclare()  # type: ignore[no-untyped-call]


@pytest.mark.parametrize("speed", [1e-300, 0.0, 1e300])
def test_absurd_speed_claims_never_lease_past_the_maximum(speed: float) -> None:
    """Issue 38, attack 2: claims of 1e-300 or 0 robot-steps/s got a 3,600-s lease. A worker
    claiming 1e-300, 0 or 1e300 (in a request, then in a result) is leased by its measured
    speed: the shortest lease after a fast job, and the dispatcher serves on."""
    with job_server() as (disp, scheduler, session):
        first = lease(session, "claimer", speed)
        ack, following = settle(session, fitted(first, "claimer", robot_steps_per_s=speed))
        assert ack.accepted, ack.reason
        assert disp.alive()
        if following is None:
            following = lease(session, "claimer")
        assert following.lease_s == POLICY.lease_min_s  # measured, whatever it claimed
        settle(session, fitted(following, "claimer", robot_steps_per_s=speed, want_next=True))
        assert disp.alive()
        normal = lease(session, "claimer")
        ack, _ = settle(session, fitted(normal, "claimer"))
        assert ack.accepted, ack.reason
        assert [w.name for w in scheduler.workers()] == ["claimer"]
        assert disp.alive() and disp.malformed == 0


# ---------------------------------------------------------------------------- server: robots


@pytest.fixture(scope="module")
def robots(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[RobotService, Any]]:
    port = free_port()
    engine = make_engine(f"sqlite:///{tmp_path_factory.mktemp('fuzz') / 'colony.db'}")
    upgrade(engine)
    router = zenoh.open(router_config(port))
    session = zenoh.open(client_config(port))
    # every example ends with a valid stuck request: no rate limit here (tested on its own)
    unlimited = RobotSettings(stuck_burst=1_000_000, stuck_per_s=1e6)
    service = RobotService(router, engine, unlimited).start()
    try:
        yield service, session
    finally:
        service.close()
        session.close()  # type: ignore[no-untyped-call]
        router.close()  # type: ignore[no-untyped-call]
        engine.dispose()


STEP = iter(range(0, 10**9, 3))


@FUZZ
@given(payload=garbage)
def test_robot_queryables_and_ack_subscriber_drop_garbage_and_keep_serving(
    robots: tuple[RobotService, zenoh.Session], payload: bytes
) -> None:
    _, session = robots
    refused_or_valid(ask(session, traces_key("fuzz-bot"), payload))
    refused_or_valid(ask(session, replace_key("fuzz-bot"), payload))
    session.put(ack_key("fuzz-bot"), payload)
    batch = trace("fuzz-bot", next(STEP))
    reply = ask(session, traces_key("fuzz-bot"), encode_trace(batch))
    assert reply.ok is not None
    ack = decode_message(reply.ok.payload.to_bytes())
    assert isinstance(ack, TraceAck) and ack.last == batch.last
    request = StuckRequest(
        robot="fuzz-bot", sha256="f" * 64, reason="fuzz", step=batch.last, nonce="1" * 32
    )
    reply = ask(session, replace_key("fuzz-bot"), encode_robot_message(request))
    assert reply.ok is not None
    answer = decode_message(reply.ok.payload.to_bytes())
    assert answer.kind == "replacement" and answer.robot == "fuzz-bot"


def test_bad_robot_liveliness_names_are_ignored(
    robots: tuple[RobotService, zenoh.Session],
) -> None:
    service, session = robots
    bad = ["bad name", "é", "x" * 129, "a:b", "~!@%+"]
    tokens = [session.liveliness().declare_token(f"evocolony/robots/{n}/alive") for n in bad]
    good = session.liveliness().declare_token(alive_key("fuzz-alive"))
    try:
        assert eventually(lambda: service.is_online("fuzz-alive"))
        ids = {r.id for r in service.robots()}
        assert not any(n in ids for n in bad)
        reply = ask(session, traces_key("fuzz-alive"), encode_trace(trace("fuzz-alive", 0)))
        assert reply.ok is not None
    finally:
        for token in [*tokens, good]:
            token.undeclare()  # type: ignore[no-untyped-call]


# ------------------------------------------------------------------------------------ worker


def _is_a_job(payload: bytes) -> bool:
    """Whether a worker would evaluate `payload` as a reply: a mutation that is still a valid
    job (other genomes, say) is work, not garbage."""
    for decoder in (decode_next_reply, lambda p: decode_result_reply(p)[1]):
        with contextlib.suppress(WireError):
            if isinstance(decoder(payload), Job):
                return True
    return False


@settings(max_examples=3, deadline=None)
@given(junk=st.lists(garbage, min_size=1, max_size=6))
def test_worker_drops_garbage_replies_and_finishes_its_job(junk: list[bytes]) -> None:
    """A hand-made server answers the worker's requests and results with garbage first. A
    mutated job that still parses as one is reported back as an invalid job, not evaluated."""
    port = free_port()
    job = _job()
    junk = [payload for payload in junk if not _is_a_job(payload)]  # a mutation still valid
    next_junk, result_junk = list(junk), list(junk)
    delivered: queue.SimpleQueue[Result] = queue.SimpleQueue()

    def on_next(query: zenoh.Query) -> None:
        with query:
            query.reply(query.key_expr, next_junk.pop() if next_junk else encode(job))

    def on_result(query: zenoh.Query) -> None:
        with query:
            if result_junk:
                query.reply(query.key_expr, result_junk.pop())
                return
            assert query.payload is not None
            result = decode(query.payload.to_bytes(), Result)
            delivered.put(result)
            query.reply(query.key_expr, encode(Ack(key=result.key, accepted=True)))

    with zenoh.open(router_config(port)) as session:
        nxt = session.declare_queryable(KEY_JOB_NEXT, on_next)
        res = session.declare_queryable(KEY_JOB_RESULT, on_result)
        try:
            with worker_thread(port, "fuzzed", fake_evaluator):
                result = delivered.get(timeout=WAIT)
                rejected = 0
                while result.error is not None:  # a mutated job that kept its key: reported
                    rejected += 1
                    assert rejected <= 2 * len(junk) and result.start is None, result.error
                    result = delivered.get(timeout=WAIT)
        finally:
            nxt.undeclare()  # type: ignore[no-untyped-call]
            res.undeclare()  # type: ignore[no-untyped-call]
    assert result.key == job.key and result.error is None and result.worker == "fuzzed"
    assert result.fitness is not None
    assert result.fitness.tobytes() == fake_fitness(job.genomes)[np.newaxis].tobytes()


# ------------------------------------------------------------------------------------- agent


@pytest.fixture(scope="module")
def agent_link(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[tuple[Agent, zenoh.Session, list[bytes]]]:
    """An agent (emulator, pty, driver) on a hand-made server whose trace replies come from
    `trace_junk` while it holds anything, then are valid acks."""
    port = free_port()
    trace_junk: list[bytes] = []

    def on_trace(query: zenoh.Query) -> None:
        with query:
            if trace_junk:
                query.reply(query.key_expr, trace_junk.pop())
                return
            assert query.payload is not None
            batch = decode_trace(query.payload.to_bytes())
            ack = TraceAck(robot=batch.robot, last=batch.last)
            query.reply(query.key_expr, encode_robot_message(ack))

    with (
        zenoh.open(router_config(port)) as router,
        BasicXEmulator(SimBody.create("paper", seed=1)) as emulator,
        BasicXDriver.open(emulator.port_path) as driver,
    ):
        traces = router.declare_queryable(KEY_TRACES, on_trace)
        agent_settings = AgentSettings(
            robot_id="fuzz-agent",
            connect=(f"tcp/127.0.0.1:{port}",),
            state_dir=tmp_path_factory.mktemp("agent"),
            backoff_max=0.2,
            request_timeout=1.0,
        )
        try:
            with Agent(agent_settings, driver) as agent:
                assert agent.connected.wait(WAIT)
                yield agent, router, trace_junk
        finally:
            traces.undeclare()  # type: ignore[no-untyped-call]


PUSH_ID = iter(range(10**9))


@FUZZ
@given(payload=garbage)
def test_agent_command_key_drops_garbage_and_accepts_the_next_push(
    agent_link: tuple[Agent, zenoh.Session, list[bytes]], payload: bytes
) -> None:
    agent, router, _ = agent_link
    acks: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    subscriber = router.declare_subscriber(
        ack_key("fuzz-agent"), lambda s: acks.put(s.payload.to_bytes())
    )
    try:
        put = router.put  # the server's own way: congestion control BLOCK
        put(command_key("fuzz-agent"), payload, congestion_control=zenoh.CongestionControl.BLOCK)
        doc = random_controller(next(PUSH_ID))
        push_id = f"fuzz-{next(PUSH_ID)}"
        push = ControllerPush(push_id=push_id, sha256=doc.sha256, document=doc.to_json())
        got: PushAck | None = None
        for _ in range(3):  # a garbage payload that parsed as a push may be acked first
            put(command_key("fuzz-agent"), encode_robot_message(push))
            try:
                while got is None:
                    message = decode_message(acks.get(timeout=5.0))
                    if isinstance(message, PushAck) and message.push_id == push_id:
                        got = message
            except queue.Empty:
                continue
            break
    finally:
        subscriber.undeclare()  # type: ignore[no-untyped-call]
    assert got is not None and got.accepted and got.sha256 == doc.sha256
    assert agent.wait_for(lambda: agent.controller is not None, WAIT)


def test_a_flood_of_push_acks_is_dropped_before_the_database_and_traces_still_land(
    robots: tuple[RobotService, zenoh.Session],
) -> None:
    """A robot's credential puts push acks as fast as it can: beyond its budget (ACK_BURST,
    then ACKS_PER_S) they are dropped before any database work, and another robot's trace
    batch is still answered at once."""
    from server.robots.service import ACK_BURST

    service, session = robots
    before = service.dropped
    ack = PushAck(robot="flood-bot", push_id="p", accepted=True, sha256="e" * 64)
    payload = encode_robot_message(ack)
    for _ in range(2_000):
        session.put(ack_key("flood-bot"), payload)
    assert eventually(lambda: service.dropped - before >= 2_000 - 2 * ACK_BURST, WAIT)
    batch = trace("calm-bot", 0)
    reply = ask(session, traces_key("calm-bot"), encode_trace(batch))
    assert reply.ok is not None
    answer = decode_message(reply.ok.payload.to_bytes())
    assert isinstance(answer, TraceAck) and answer.last == batch.last


@settings(max_examples=3, deadline=None)
@given(junk=st.lists(garbage, min_size=1, max_size=5))
def test_agent_drops_garbage_trace_acks_and_delivers_later(
    agent_link: tuple[Agent, zenoh.Session, list[bytes]], junk: list[bytes]
) -> None:
    agent, _, trace_junk = agent_link
    trace_junk.extend(junk)
    assert agent.wait_for(lambda: not trace_junk, WAIT)
    delivered = agent.delivered
    assert agent.wait_for(lambda: agent.delivered > delivered, WAIT)
    assert agent.status().serial_ok


def test_the_templates_are_messages_of_this_protocol() -> None:
    """The fuzzers' template messages really are valid, so mutations start from the real thing."""
    assert NAME_PATTERN.match("fuzz-agent") and decode_trace(VALID[5]).robot == "template-bot"
    job = decode_next_reply(VALID[2])
    assert isinstance(job, Job) and job.key == _job().key
    assert decode(VALID[0], JobRequest).worker == GARBLER
    assert decode(VALID[1], Result).fitness is not None
    assert decode_result_reply(VALID[3]) == (Ack(key=job.key, accepted=True), None)
    assert decode_next_reply(VALID[4]) == Idle(reason="no job")
