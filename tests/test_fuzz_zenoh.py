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
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robot_agent.agent import Agent, AgentSettings
from robot_agent.driver import BasicXDriver
from robot_agent.emulator import BasicXEmulator
from robot_agent.sim_body import SimBody
from schemas.robots import (
    KEY_REPLACE,
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
)
from schemas.robots import encode_message as encode_robot_message
from schemas.wire import (
    ALLOWED_DTYPES,
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    MAGIC,
    NAME_PATTERN,
    Ack,
    Job,
    JobKey,
    JobRequest,
    Result,
    WireError,
    decode_ack,
    decode_next_reply,
    decode_result,
    decode_result_reply,
    encode_frame,
    encode_job,
    encode_message,
    encode_result,
    team_key,
)
from server.db import make_engine, upgrade
from server.dispatch import Dispatcher
from server.robots import RobotService
from tests.helpers import eventually, free_port
from tests.test_agent import random_controller
from tests.test_dispatch import (
    CONFIG,
    WAIT,
    MemorySource,
    client_config,
    dispatch_settings,
    fake_evaluator,
    worker_thread,
)
from tests.test_robots_server import router_config

FUZZ = settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
KINDS = ["next", "job", "idle", "ack", "result", "push", "stop", "trace", "trace-ack", "stuck"]
KINDS += ["replacement", "", "\x00"]
STATUS = RobotStatus(state="running", steps=3, sha256=None, serial_ok=True)


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
    )


def _job() -> Job:
    source = MemorySource()
    return source.jobs[0]


class EndlessSource:
    """A JobSource that always has the same job: every valid request must get it."""

    def __init__(self) -> None:
        self.job = _job()
        self.completed = 0

    def lease(self, worker: str) -> Job | None:
        return self.job

    def complete(self, result: Result) -> bool:
        self.completed += 1
        return True

    def fail(self, key: JobKey, error: str) -> None:
        raise AssertionError(f"no error result was sent: {error}")

    def release(self, key: JobKey) -> None:
        pass

    def flush(self) -> None:
        pass


VALID: list[bytes] = [
    encode_message(JobRequest(worker="template", holding=())),
    encode_result(
        Result(_job().key, "template", np.zeros(3), np.zeros((3, 2, 4)), start=0, stop=3)
    ),
    encode_job(_job()),
    encode_message(Ack(key=_job().key, accepted=True)),
    encode_trace(trace("template-bot", 0)),
    encode_robot_message(StuckRequest(robot="template-bot", sha256=None, reason="x", step=1)),
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
        replies = list(session.get(key, payload=payload, timeout=5.0))
        if replies:
            return replies[0]
        deadline.wait(0.05)
    raise AssertionError(f"no reply on {key}")


def refused_or_valid(reply: zenoh.Reply) -> None:
    """Garbage is answered with reply_err("malformed: ..."); a payload that happens to be a
    valid message gets an ordinary reply."""
    if reply.err is not None:
        assert reply.err.payload.to_bytes().startswith(b"malformed")
    else:
        assert reply.ok is not None


# ------------------------------------------------------------------------------ server: jobs


@pytest.fixture(scope="module")
def dispatcher() -> Iterator[tuple[Dispatcher, zenoh.Session]]:
    port = free_port()
    with (
        Dispatcher(dispatch_settings(port), EndlessSource()) as disp,
        zenoh.open(client_config(port)) as session,
    ):
        yield disp, session


def lease(session: zenoh.Session) -> Job:
    """A valid request: the first job again (a request without `holding` releases the last)."""
    reply = ask(session, KEY_JOB_NEXT, encode_message(JobRequest(worker="fuzzer")))
    assert reply.ok is not None, reply.err and reply.err.payload.to_bytes()
    job = decode_next_reply(reply.ok.payload.to_bytes())
    assert isinstance(job, Job) and job.key.run_id == 1
    return job


@FUZZ
@given(payload=garbage)
def test_job_queryables_drop_garbage_and_keep_serving(
    dispatcher: tuple[Dispatcher, zenoh.Session], payload: bytes
) -> None:
    disp, session = dispatcher
    before = disp.malformed
    for key in (KEY_JOB_NEXT, KEY_JOB_RESULT):
        refused_or_valid(ask(session, key, payload))
    job = lease(session)
    fitness = np.arange(job.stop - job.start, dtype=np.float64)
    components = np.zeros((len(fitness), CONFIG.trials, 4))
    result = Result(job.key, "fuzzer", fitness, components, start=job.start, stop=job.stop)
    reply = ask(session, KEY_JOB_RESULT, encode_result(result))
    assert reply.ok is not None
    ack = decode_ack(reply.ok.payload.to_bytes())
    assert ack.key == job.key and ack.accepted
    assert disp.malformed >= before


def test_bad_worker_liveliness_names_are_dropped(
    dispatcher: tuple[Dispatcher, zenoh.Session],
) -> None:
    disp, session = dispatcher
    before = disp.malformed
    bad = ["bad name", "é", "x" * 129, "a:b", "~!@%+", "a/b/c"]
    tokens = [session.liveliness().declare_token(f"evocolony/workers/{n}") for n in bad]
    good = session.liveliness().declare_token("evocolony/workers/fuzz-good")
    try:
        assert eventually(lambda: "fuzz-good" in {w.name for w in disp.workers()})
        assert eventually(lambda: disp.malformed >= before + len(bad) - 1)
        names = {w.name for w in disp.workers()}
        assert not any(n in names for n in bad)
        lease(session)
    finally:
        for token in [*tokens, good]:
            token.undeclare()  # type: ignore[no-untyped-call]


# ---------------------------------------------------------------------------- server: robots


@pytest.fixture(scope="module")
def robots(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[RobotService, Any]]:
    port = free_port()
    engine = make_engine(f"sqlite:///{tmp_path_factory.mktemp('fuzz') / 'colony.db'}")
    upgrade(engine)
    router = zenoh.open(router_config(port))
    session = zenoh.open(client_config(port))
    service = RobotService(router, engine).start()
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
    refused_or_valid(ask(session, KEY_TRACES, payload))
    refused_or_valid(ask(session, KEY_REPLACE, payload))
    session.put(ack_key("fuzz-bot"), payload)
    batch = trace("fuzz-bot", next(STEP))
    reply = ask(session, KEY_TRACES, encode_trace(batch))
    assert reply.ok is not None
    ack = decode_message(reply.ok.payload.to_bytes())
    assert isinstance(ack, TraceAck) and ack.last == batch.last
    request = StuckRequest(robot="fuzz-bot", sha256="f" * 64, reason="fuzz", step=batch.last)
    reply = ask(session, KEY_REPLACE, encode_robot_message(request))
    assert reply.ok is not None
    answer = decode_message(reply.ok.payload.to_bytes())
    assert answer.kind == "replacement" and answer.robot == "fuzz-bot"


def test_bad_robot_liveliness_names_are_ignored(
    robots: tuple[RobotService, zenoh.Session],
) -> None:
    service, session = robots
    bad = ["bad name", "é", "x" * 129, "a:b", "~!@%+"]
    tokens = [session.liveliness().declare_token(f"evocolony/robots/alive/{n}") for n in bad]
    good = session.liveliness().declare_token(alive_key("fuzz-alive"))
    try:
        assert eventually(lambda: service.is_online("fuzz-alive"))
        ids = {r.id for r in service.robots()}
        assert not any(n in ids for n in bad)
        reply = ask(session, KEY_TRACES, encode_trace(trace("fuzz-alive", 0)))
        assert reply.ok is not None
    finally:
        for token in [*tokens, good]:
            token.undeclare()  # type: ignore[no-untyped-call]


# ------------------------------------------------------------------------------------ worker


def _is_a_job(payload: bytes) -> bool:
    """Whether a worker would evaluate `payload` as a reply: a mutation that is still a valid
    job (other genomes, say) is work, not garbage."""
    for decode in (decode_next_reply, lambda p: decode_result_reply(p)[1]):
        with contextlib.suppress(WireError):
            if isinstance(decode(payload), Job):
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
            query.reply(KEY_JOB_NEXT, next_junk.pop() if next_junk else encode_job(job))

    def on_result(query: zenoh.Query) -> None:
        with query:
            if result_junk:
                query.reply(KEY_JOB_RESULT, result_junk.pop())
                return
            assert query.payload is not None
            result = decode_result(query.payload.to_bytes())
            delivered.put(result)
            query.reply(KEY_JOB_RESULT, encode_message(Ack(key=result.key, accepted=True)))

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
    assert result.key == job.key and result.error is None
    assert result.fitness is not None
    assert np.array_equal(result.fitness, job.genomes.sum(axis=1))


@settings(max_examples=5, deadline=None)
@given(junk=st.lists(garbage, min_size=1, max_size=4))
def test_team_members_drop_garbage_on_their_keys_and_finish_the_generation(
    junk: list[bytes],
) -> None:
    """Garbage on both members' team keys before a generation's exchange: each logs and
    drops it and still gets the other's slice."""
    from tests.test_team import members, router, run_team, whole

    names = ("lead", "member")
    with router() as port, members(port, names) as sessions:
        for name in names:
            for payload in junk:
                sessions[0][0].put(team_key(name), payload)
        out = run_team(sessions, names, 2)
    for results, _ in out.values():
        assert len(results) == 2
        for g, result in enumerate(results):
            assert result is not None and result[0].tobytes() == whole(g)[0].tobytes()
    assert sorted(out) == [0, 1]


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
                query.reply(KEY_TRACES, trace_junk.pop())
                return
            assert query.payload is not None
            batch = decode_trace(query.payload.to_bytes())
            ack = TraceAck(robot=batch.robot, last=batch.last)
            query.reply(KEY_TRACES, encode_robot_message(ack))

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


def test_replies_are_names_of_this_protocol() -> None:
    """The fuzzers' template messages really are valid, so mutations start from the real thing."""
    assert NAME_PATTERN.match("fuzz-agent") and decode_trace(VALID[4]).robot == "template-bot"
    assert isinstance(decode_next_reply(VALID[2]), Job)
