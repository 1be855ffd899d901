"""Robot bindings and trace integrity (issue 24), attacked with real parts: real zenoh on
127.0.0.1, real SQLite files, agents as threads over BasicX emulator ptys, a real uvicorn.

A hijacked or replayed replacement, far-ahead and foreign trace batches, a fake ack, a disk
that fills up under the trace store, a server clock that ran ahead, a STOP with a stale
sequence number, and forgetting a stale robot.
"""

from __future__ import annotations

import logging
import queue
import secrets
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh
from sqlalchemy import event, select
from typer.testing import CliRunner

from colony.cli import app as cli
from evorobotics.document import ControllerDocument
from robot_agent.stuck import StuckConfig
from schemas.answer import CONSOLIDATION, TARGET
from schemas.network import NetworkSpec
from schemas.robots import (
    ControllerPush,
    PushAck,
    Replacement,
    RobotStatus,
    StopCommand,
    StuckRequest,
    TraceBatch,
    TrackerPose,
    ack_key,
    alive_key,
    command_key,
    decode_message,
    encode_message,
    encode_trace,
    replace_key,
    traces_key,
    tracker_key,
)
from schemas.wire import decode_frame, encode_frame
from server.core.db import make_engine, upgrade
from server.core.keys import load_or_create_key
from server.core.models import Robot
from server.core.settings import Settings
from server.robots.service import RobotService
from server.robots.settings import RobotSettings
from server.robots.signing import Signer
from server.robots.store import FieldStatsRow, RobotStateRow, TraceRow
from server.runs import crud
from tests.helpers import (
    WAIT,
    Colony,
    Link,
    client_config,
    constant_drive,
    eventually,
    free_port,
    online,
    random_controller,
    robot_link,
    router_config,
    save,
    serving,
    virtual_robot,
)

TOKEN = "robot-token"
DAY_NS = 86_400 * 10**9


@pytest.fixture(scope="module")
def colony(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Colony]:
    """A real server with a token and no zenoh of its own: each test opens a router with a
    RobotService on its database."""
    tmp = tmp_path_factory.mktemp("integrity")
    db_url = f"sqlite:///{tmp / 'colony.db'}"
    settings = Settings(db_url=db_url, port=free_port(), executors=0, zenoh=False, api_token=TOKEN)
    with serving(settings) as (url, app):
        yield Colony(url, db_url, 0, app, tmp)


def _ask(session: zenoh.Session, key: str, payload: bytes) -> zenoh.Reply:
    replies = list(
        session.get(key, payload=payload, timeout=WAIT, target=TARGET, consolidation=CONSOLIDATION)
    )
    assert len(replies) == 1
    return replies[0]


def _batch(robot: str, boot: int, first: int, n: int, **changes: Any) -> TraceBatch:
    fields: dict[str, Any] = {
        "robot": robot,
        "boot": boot,
        "controllers": (),
        "status": RobotStatus(state="escaping", steps=first + n, sha256=None, serial_ok=True),
        "steps": np.arange(first, first + n, dtype=np.int64),
        "whiskers": np.zeros((n, 5), np.uint8),
        "motors": np.full((n, 2), -0.6),
        "controller": np.full(n, -1, np.int32),
        "fresh": np.zeros(n, np.bool_),
        "times": np.full(n, time.time()),
        "poses": np.zeros((n, 3)),
        "pose_source": "odometry",
    }
    fields.update(changes)
    return TraceBatch(**fields)


def _stored_steps(service: RobotService, robot: str, boot: int) -> np.ndarray:
    with service.sessions() as db:
        rows = db.scalars(
            select(TraceRow)
            .where(TraceRow.robot_id == robot, TraceRow.boot == boot)
            .order_by(TraceRow.first)
        ).all()
    if not rows:
        return np.empty(0, np.int64)
    return np.concatenate([np.frombuffer(r.steps, "<i8") for r in rows])


def _signer(tmp: Path, clock_offset_ns: int = 0) -> Signer:
    return Signer.from_file(tmp / "server-key.pem", clock=lambda: time.time_ns() + clock_offset_ns)


def _store_controller(link: Link, doc: ControllerDocument) -> None:
    with link.service.sessions.begin() as db:
        crud.put_controller(
            db,
            sha256=doc.sha256,
            document=doc.to_json(),
            run_id=None,
            generation=None,
            fitness=None,
        )


# ---------------------------------------------------------------------------- replacements


def test_a_replacement_for_another_request_unsigned_or_replayed_is_refused(
    colony: Colony, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The only answerer on the robot's replace key is a rogue holding the server's valid
    signatures: one made for another request's nonce, an unsigned one, then (after it relays
    one genuine answer) that genuine answer replayed to the next request."""
    caplog.set_level(logging.WARNING, logger="robot_agent.agent")
    signer = _signer(tmp_path / "server")
    wall = constant_drive(0.9, 0.9, NetworkSpec())
    rogue_doc = random_controller(21, NetworkSpec())
    genuine = constant_drive(0.8, 0.8, NetworkSpec())  # also drives into the wall
    save(tmp_path / "agent", wall)
    requests: queue.SimpleQueue[StuckRequest] = queue.SimpleQueue()
    answers: list[bytes] = []

    def signed(doc: ControllerDocument, nonce: str) -> bytes:
        text = doc.to_json()
        seq, sig = signer.sign(kind="replacement", robot="r-hijack", push_id=nonce, document=text)
        reply = Replacement(robot="r-hijack", document=text, seq=seq, signature=sig)
        return encode_message(reply)

    def rogue(query: zenoh.Query) -> None:
        with query:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            request = decode_message(payload)
            assert isinstance(request, StuckRequest)
            requests.put(request)
            step = len(answers)
            if step == 0:  # validly signed, for a request the rogue made itself
                answer = signed(rogue_doc, secrets.token_hex(16))
            elif step == 1:  # unsigned
                answer = encode_message(Replacement(robot="r-hijack", document=rogue_doc.to_json()))
            elif step == 2:  # the genuine answer to this request
                answer = signed(genuine, request.nonce)
            elif step == 3:  # that genuine answer again, to the next request
                answer = answers[2]
            else:
                answer = encode_message(Replacement(robot="r-hijack", document=None))
            answers.append(answer)
            query.reply(query.key_expr, answer)

    with robot_link(colony) as link:
        link.service.close()  # no server: the rogue is the only answerer
        queryable = link.router.declare_queryable(replace_key("r-hijack"), rogue)
        try:
            with virtual_robot(
                "r-hijack",
                link,
                tmp_path / "agent",
                stuck=StuckConfig(contact_steps=5),
                server_key=signer.public_pem.encode(),
            ) as (agent, _):
                nonces = [requests.get(timeout=WAIT).nonce for _ in range(2)]
                assert agent.controller == wall  # neither the foreign nor the unsigned one
                assert agent.wait_for(lambda: agent.controller == genuine, WAIT)
                seq = agent.verifier.last_seq if agent.verifier else None
                nonces += [requests.get(timeout=WAIT).nonce for _ in range(2)]
                assert agent.controller == genuine
                assert agent.verifier is not None and agent.verifier.last_seq == seq
        finally:
            queryable.undeclare()  # type: ignore[no-untyped-call]
    assert len(set(nonces)) == 4 and all(len(n) == 32 for n in nonces)
    refusals = [r.getMessage() for r in caplog.records if "refusing the replacement" in r.message]
    assert len(refusals) >= 3, refusals
    assert "bad signature" in refusals[0] and "unsigned" in refusals[1]
    assert "bad signature" in refusals[2]  # the replay: signed over another nonce


# ---------------------------------------------------------------------------- traces


def test_fake_trace_batches_are_refused_and_the_real_ones_stored(
    colony: Colony, tmp_path: Path
) -> None:
    doc = random_controller(22, NetworkSpec())
    save(tmp_path, doc)
    with (
        robot_link(colony) as link,
        virtual_robot("r-fake", link, tmp_path) as (agent, _),
        zenoh.open(client_config(link.port)) as rogue,
    ):
        _store_controller(link, doc)
        assert agent.wait_for(lambda: agent.delivered >= 20, WAIT)
        boot, key = agent.boot, traces_key("r-fake")
        far = agent.steps + 5000
        gap = np.concatenate([np.arange(5), np.arange(6, 11)]).astype(np.int64)
        ahead = np.full(10, time.time() + 3600)  # a clock an hour fast
        fakes = [
            ("beyond", _batch("r-fake", boot, 10**12, 600)),
            ("ahead of the robot's clock", _batch("r-fake", boot, 40_000, 600)),
            ("not contiguous", _batch("r-fake", boot, far, 10)),
            ("jumps", _batch("r-fake", boot + 1000, 0, 600)),
            ("ahead of the robot's clock", _batch("r-fake", boot + 1, 0, 600)),
            ("not consecutive", _batch("r-fake", boot, 0, 10, steps=gap)),
            ("ahead of the server's clock", _batch("r-fake", boot, 0, 10, times=ahead)),
        ]
        for reason, batch in fakes:
            reply = _ask(rogue, key, encode_trace(batch))
            assert reply.err is not None, reason
            assert reason in reply.err.payload.to_bytes().decode()
        header, arrays = decode_frame(encode_trace(_batch("r-fake", boot, 0, 3)))
        arrays["motors"] = np.full((3, 2), 1.5)  # beyond what a wheel can be told
        reply = _ask(rogue, key, encode_frame(header, arrays))
        assert reply.err is not None and b"within [-1, 1]" in reply.err.payload.to_bytes()
        delivered = agent.delivered
        assert agent.wait_for(lambda: agent.delivered >= delivered + 30, WAIT)
        assert agent.buffered() < 20 and agent.dropped == 0
        steps = _stored_steps(link.service, "r-fake", boot)
        assert np.array_equal(steps, np.arange(steps.shape[0]))  # every real sample, no gap
        assert steps[-1] >= delivered + 29
        for other in (boot + 1, boot + 1000):
            assert _stored_steps(link.service, "r-fake", other).shape[0] == 0
        assert link.service.replay("r-fake").identical


@pytest.mark.parametrize("window", [3600.0, 0.0])
def test_a_burst_of_new_boots_evicts_no_acknowledged_sample(
    colony: Colony, tmp_path: Path, window: float
) -> None:
    """Issue 38, attack 4: 420 batches, each one boot higher, were acknowledged in 5.4 s and
    evicted every real sample. All boots of a robot together now add samples no faster than its
    clock (the rest is refused), and samples that arrived within `retention_window_s` are never
    evicted; with a window of 0 the newest `retention_samples` are kept, as before."""
    settings = RobotSettings(
        push_timeout=5.0, retention_samples=120, retention_window_s=window, max_backlog=400
    )
    doc = random_controller(33, NetworkSpec())
    save(tmp_path, doc)
    with robot_link(colony, settings=settings) as link:
        with virtual_robot("r-evict", link, tmp_path, period=0.01) as (agent, _):
            assert agent.wait_for(lambda: agent.delivered >= 150, WAIT)
            boot = agent.boot
            real = _stored_steps(link.service, "r-evict", boot)
            refusals = []
            with zenoh.open(client_config(link.port)) as rogue:
                for k in range(1, 60):
                    reply = _ask(rogue, traces_key("r-evict"), encode_trace(
                        _batch("r-evict", boot + k, 0, 100)
                    ))  # fmt: skip
                    if reply.err is not None:
                        refusals.append(reply.err.payload.to_bytes().decode())
            kept = _stored_steps(link.service, "r-evict", boot)
        assert any("more than the robot's clock allows" in r for r in refusals)
        if window:
            assert set(real.tolist()) <= set(kept.tolist())  # every acknowledged sample stays
        else:
            with link.service.sessions() as db:
                counts = db.scalars(select(TraceRow.count).where(TraceRow.robot_id == "r-evict"))
                assert sum(counts) <= 120 + 100  # the newest, to within the newest batch


def test_a_failed_commit_is_never_acknowledged(tmp_path: Path) -> None:
    """The disk fills up under the trace store (SQLite's max_page_count): the agent keeps its
    samples, and once space is back they all land, with no gap."""
    db_url = f"sqlite:///{tmp_path / 'full.db'}"
    engine = make_engine(db_url)
    upgrade(engine)
    limit = [1 << 30]

    @event.listens_for(engine, "checkout")
    def _limit(dbapi_connection: Any, _record: Any, _proxy: Any) -> None:
        cursor = dbapi_connection.cursor()
        cursor.execute(f"PRAGMA max_page_count={limit[0]}")  # never below the file's size
        cursor.close()

    port = free_port()
    save(tmp_path / "agent", random_controller(23, NetworkSpec()))
    router = zenoh.open(router_config(port))
    try:
        service = RobotService(router, engine, RobotSettings(push_timeout=5.0)).start()
        link = Link(router, service, f"tcp/127.0.0.1:{port}", port)
        try:
            with virtual_robot("r-full", link, tmp_path / "agent") as (agent, _):
                assert agent.wait_for(lambda: agent.delivered >= 20, WAIT)
                limit[0] = 1  # the disk is full
                assert agent.wait_for(lambda: agent.buffered() >= 60, WAIT)
                stuck_at = agent.delivered
                steps = _stored_steps(service, "r-full", agent.boot)
                assert steps.shape[0] == stuck_at  # acknowledged: exactly what is committed
                assert np.array_equal(steps, np.arange(steps.shape[0]))
                limit[0] = 1 << 30  # space again
                # a batch taken before the 60th sample may land first: wait for all 60
                assert agent.wait_for(lambda: agent.delivered >= stuck_at + 60, WAIT)
                assert agent.dropped == 0
                steps = _stored_steps(service, "r-full", agent.boot)
                assert np.array_equal(steps, np.arange(steps.shape[0]))  # no gap
                assert steps[-1] >= stuck_at + 60 - 1
        finally:
            service.close()
    finally:
        router.close()  # type: ignore[no-untyped-call]
        engine.dispose()


# ---------------------------------------------------------------------------- acks and seq


def test_a_fake_ack_on_another_robots_key_does_not_complete_a_push(
    colony: Colony, tmp_path: Path
) -> None:
    """Robot A is absent; a rogue fakes its liveliness, reads the push and acks it for A
    on B's key: the push is not accepted. The same ack on A's own key would be."""
    doc = random_controller(24)
    settings = RobotSettings(push_timeout=1.0)
    with robot_link(colony, settings=settings) as link, zenoh.open(client_config(link.port)) as z:
        _store_controller(link, doc)
        pushes: queue.SimpleQueue[str] = queue.SimpleQueue()

        def on_command(sample: zenoh.Sample) -> None:
            message = decode_message(sample.payload.to_bytes())
            assert isinstance(message, ControllerPush)
            pushes.put(message.push_id)

        subscriber = z.declare_subscriber(command_key("r-absent"), on_command)
        token = z.liveliness().declare_token(alive_key("r-absent"))
        try:
            assert eventually(lambda: link.service.is_online("r-absent"), WAIT)
            results = []
            for key in (ack_key("r-other"), ack_key("r-absent")):
                answer: queue.SimpleQueue[Any] = queue.SimpleQueue()
                thread = _pushing(link.service, "r-absent", doc.sha256, answer)
                push_id = pushes.get(timeout=WAIT)
                ack = PushAck(robot="r-absent", push_id=push_id, accepted=True, sha256=doc.sha256)
                z.put(key, encode_message(ack))
                results.append(answer.get(timeout=WAIT))
                thread.join(WAIT)
        finally:
            token.undeclare()  # type: ignore[no-untyped-call]
            subscriber.undeclare()  # type: ignore[no-untyped-call]
    forged, own = results
    assert not forged.accepted and not forged.acknowledged
    assert own.accepted  # the rogue on A's own key: what zenoh's access control must stop


def _pushing(
    service: RobotService, robot: str, sha: str, answer: queue.SimpleQueue[Any]
) -> threading.Thread:
    thread = threading.Thread(target=lambda: answer.put(service.push(robot, sha256=sha)))
    thread.start()
    return thread


def test_pushes_and_stop_after_the_server_clock_ran_ahead_and_was_corrected(
    colony: Colony, tmp_path: Path
) -> None:
    key_dir = tmp_path / "server"
    first, second = random_controller(25), random_controller(26)
    ahead = _signer(key_dir, clock_offset_ns=DAY_NS)
    with robot_link(colony, signer=ahead) as link:
        _store_controller(link, first)
        _store_controller(link, second)
        pem = ahead.public_pem.encode()
        with virtual_robot("r-clock", link, tmp_path / "agent", server_key=pem) as (agent, _):
            assert eventually(lambda: link.service.is_online("r-clock"), WAIT)
            pushed = link.service.push("r-clock", sha256=first.sha256)
            assert pushed.accepted, pushed
    # the clock is corrected (a day back) and the server restarts with the same key
    corrected = _signer(key_dir)
    assert corrected.last_seq == ahead.last_seq > time.time_ns()
    with (
        robot_link(colony, signer=corrected) as link,
        virtual_robot("r-clock", link, tmp_path / "agent") as (agent, _),
    ):
        assert eventually(lambda: link.service.is_online("r-clock"), WAIT)
        pushed = link.service.push("r-clock", sha256=second.sha256)
        assert pushed.accepted, pushed
        assert agent.controller == second
        stopped = link.service.stop_robot("r-clock")
        assert stopped.accepted and agent.state == "stopped"


def test_a_stop_with_a_stale_seq_stops_and_never_opens_a_replay(
    colony: Colony, tmp_path: Path
) -> None:
    signer = _signer(tmp_path / "server")
    stale = Signer(load_or_create_key(tmp_path / "server" / "server-key.pem"), clock=lambda: 5)
    doc, other = random_controller(27), random_controller(28)
    save(tmp_path / "agent", doc)
    with (
        robot_link(colony, signer=signer) as link,
        virtual_robot(
            "r-stale", link, tmp_path / "agent", server_key=signer.public_pem.encode()
        ) as (agent, _),
    ):
        _store_controller(link, other)
        assert eventually(lambda: link.service.is_online("r-stale"), WAIT)
        assert link.service.push("r-stale", sha256=other.sha256).accepted
        assert agent.verifier is not None
        last = agent.verifier.last_seq
        acks: queue.SimpleQueue[PushAck] = queue.SimpleQueue()

        def on_ack(sample: zenoh.Sample) -> None:
            message = decode_message(sample.payload.to_bytes())
            if isinstance(message, PushAck):
                acks.put(message)

        subscriber = link.router.declare_subscriber(ack_key("r-stale"), on_ack)
        try:
            seq, sig = stale.sign(kind="stop", robot="r-stale", push_id="stop-1", document=None)
            stop = StopCommand(push_id="stop-1", seq=seq, signature=sig)
            link.router.put(command_key("r-stale"), encode_message(stop))
            ack = acks.get(timeout=WAIT)
            assert ack.push_id == "stop-1" and ack.accepted
            assert agent.state == "stopped" and agent.verifier.last_seq == last
            text = doc.to_json()
            seq, sig = stale.sign(kind="push", robot="r-stale", push_id="old", document=text)
            push = ControllerPush(
                push_id="old", sha256=doc.sha256, document=text, seq=seq, signature=sig
            )
            link.router.put(command_key("r-stale"), encode_message(push))
            ack = acks.get(timeout=WAIT)
            assert not ack.accepted and "replayed" in ack.reason
            assert agent.state == "stopped" and agent.verifier.last_seq == last
        finally:
            subscriber.undeclare()  # type: ignore[no-untyped-call]
        assert link.service.push("r-stale", sha256=other.sha256).accepted


# ---------------------------------------------------------------------------- forgetting


def test_forget_a_stale_robot(colony: Colony, tmp_path: Path) -> None:
    doc = random_controller(29, NetworkSpec())
    auth = {"Authorization": f"Bearer {TOKEN}"}
    with (
        robot_link(colony) as link,
        httpx.Client(base_url=colony.url, timeout=30) as client,
    ):
        _store_controller(link, doc)
        with virtual_robot("r-gone", link, tmp_path) as (agent, _):
            assert eventually(lambda: link.service.is_online("r-gone"), WAIT)
            assert link.service.push("r-gone", sha256=doc.sha256).accepted  # it counts
            pushed = agent.delivered
            assert agent.wait_for(lambda: agent.delivered >= pushed + 30, WAIT)
            busy = client.delete("/api/robots/r-gone", headers=auth)
            assert busy.status_code == 409 and "online" in busy.json()["detail"]
        assert eventually(lambda: not online(client, "r-gone"), WAIT)
        assert client.delete("/api/robots/r-gone").status_code == 401
        gone = client.delete("/api/robots/r-gone", headers=auth)
        assert gone.status_code == 204 and gone.content == b""
        assert client.get("/api/robots/r-gone").status_code == 404
        assert "r-gone" not in [r["id"] for r in client.get("/api/robots").json()]
        assert client.delete("/api/robots/r-gone", headers=auth).status_code == 404
        with link.service.sessions() as db:
            assert db.scalars(select(TraceRow).where(TraceRow.robot_id == "r-gone")).first() is None
            assert db.get(RobotStateRow, "r-gone") is None
            stats = db.get(FieldStatsRow, doc.sha256)
            assert stats is not None and stats.steps >= 20  # the controller's record stays
        # the agent comes back later (same boot numbering): it is registered afresh
        with virtual_robot("r-gone", link, tmp_path) as (agent, _):
            assert agent.wait_for(lambda: agent.delivered >= 10, WAIT)
        assert eventually(lambda: not online(client, "r-gone"), WAIT)
        runner = CliRunner()
        args = ["robot", "forget", "r-gone", "--server", colony.url]
        refused = runner.invoke(cli, args, env={"COLONY_API_TOKEN": ""})
        assert refused.exit_code == 1 and "401" in refused.output
        done = runner.invoke(cli, args, env={"COLONY_API_TOKEN": TOKEN})
        assert done.exit_code == 0 and "forgotten" in done.output, done.output
        missing = runner.invoke(cli, args, env={"COLONY_API_TOKEN": TOKEN})
        assert missing.exit_code == 1 and "404" in missing.output


def test_a_robot_naming_a_controller_it_was_never_given_raises_no_field_statistics(
    colony: Colony,
) -> None:
    """Issue 38, attack 5: any robot raised any controller's field statistics by naming it (50
    stuck events in seconds). Its stuck requests and trace batches are still its own record,
    but only a controller the server gave the robot counts for the controller."""
    doc = random_controller(31, NetworkSpec())
    with robot_link(colony) as link, zenoh.open(client_config(link.port)) as rogue:
        _store_controller(link, doc)
        with link.service.sessions.begin() as db:  # known to the colony, as its agent made it
            db.add(Robot(id="r-claim", status="online"))
        for k in range(5):
            request = StuckRequest(
                robot="r-claim", sha256=doc.sha256, reason="x", step=k, nonce=secrets.token_hex(16)
            )
            assert _ask(rogue, replace_key("r-claim"), encode_message(request)).ok is not None
        claimed = _batch(
            "r-claim", 0, 0, 50, controllers=(doc.sha256,), controller=np.zeros(50, np.int32)
        )
        assert _ask(rogue, traces_key("r-claim"), encode_trace(claimed)).ok is not None
        assert [e.controller_sha256 for e in link.service.stuck_events("r-claim").events] == [
            doc.sha256
        ] * 5
        assert _stored_steps(link.service, "r-claim", 0).shape[0] == 50
        assert link.service.field_stats(doc.sha256) is None


def test_a_megabyte_sha256_from_a_robot_is_refused_and_stores_nothing(
    colony: Colony, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 38, attack 5: a robot credential's sha256 fields were strings of any length, stored
    and logged as sent. A stuck request and a trace batch carrying a 1 MB sha256 over zenoh are
    refused as malformed, naming the field; no stuck event, sample or megabyte log line."""
    huge = "f" * 1_000_000
    with robot_link(colony) as link, zenoh.open(client_config(link.port)) as rogue:
        with link.service.sessions.begin() as db:  # known to the colony, as its agent made it
            db.add(Robot(id="r-huge", status="online"))
        request = StuckRequest(
            robot="r-huge", sha256=None, reason="x", step=1, nonce=secrets.token_hex(16)
        )
        stuck = encode_frame({**request.model_dump(mode="json"), "sha256": huge})
        header, arrays = decode_frame(encode_trace(_batch("r-huge", 0, 0, 10)))
        traces = encode_frame({**header, "controllers": [huge]}, arrays)
        sent = [
            (replace_key("r-huge"), stuck, "StuckRequest: 1 validation error for StuckRequest\nsha256"),
            (traces_key("r-huge"), traces, "trace header: 1 validation error for TraceHeader\ncontrollers.0"),
        ]  # fmt: skip
        for key, payload, field in sent:
            assert len(payload) > 1_000_000
            reply = _ask(rogue, key, payload)
            assert reply.err is not None, key
            why = reply.err.payload.to_bytes().decode()
            assert why.startswith(f"malformed: {field}") and len(why) < 10_000, why
        assert link.service.stuck_events("r-huge").events == []
        assert _stored_steps(link.service, "r-huge", 0).shape[0] == 0
        with link.service.sessions() as db:
            state = db.get(RobotStateRow, "r-huge")
            assert state is None or state.stuck_events == 0
    assert all(len(r.getMessage()) < 10_000 for r in caplog.records)


def test_a_push_acknowledged_after_its_timeout_still_counts_for_its_controller(
    colony: Colony, tmp_path: Path
) -> None:
    """A push whose acknowledgement comes after the caller stopped waiting (it applies at a
    step boundary) still ran on the robot: its steps count for the controller it pushed."""
    doc = random_controller(37, NetworkSpec())
    with robot_link(colony) as link, virtual_robot("r-late", link, tmp_path) as (agent, _):
        _store_controller(link, doc)
        assert eventually(lambda: link.service.is_online("r-late"), WAIT)
        out = link.service.push("r-late", sha256=doc.sha256, timeout=1e-4)
        assert not out.acknowledged  # the caller gave up first
        assert agent.wait_for(
            lambda: agent.controller is not None and agent.controller.sha256 == doc.sha256, WAIT
        )
        delivered = agent.delivered
        assert agent.wait_for(lambda: agent.delivered >= delivered + 20, WAIT)

        def counted() -> bool:
            stats = link.service.field_stats(doc.sha256)
            return stats is not None and stats.robot_hours > 0

        assert eventually(counted, WAIT)


def test_each_sample_takes_the_trackers_newest_pose_and_bad_poses_are_dropped(
    colony: Colony,
) -> None:
    """Issue 37: a sample stores the tracker's newest pose at or before its time, if at most
    0.5 s old (else the batch keeps the robot's own poses). A malformed pose, one whose key
    names another robot, one of a robot not online and one out of order are dropped."""
    t0 = time.time()
    with (
        robot_link(colony) as link,
        zenoh.open(client_config(link.port)) as robot,
        zenoh.open(client_config(link.port)) as tracker,
    ):
        token = robot.liveliness().declare_token(alive_key("r-trk"))
        assert eventually(lambda: link.service.is_online("r-trk"), WAIT)

        def pose(robot: str, at: float, x: float) -> bytes:
            return encode_message(TrackerPose(robot=robot, at=at, x=x, y=0, theta=0))

        hostile = [
            (tracker_key("r-trk"), b"garbage"),
            (tracker_key("r-trk"), pose("r-else", t0, 9)),
            (tracker_key("r-off"), pose("r-off", t0, 9)),
        ]
        good = [(tracker_key("r-trk"), pose("r-trk", t0 + k / 10, k)) for k in range(10)]
        late = (tracker_key("r-trk"), pose("r-trk", t0 + 0.45, 9))
        for key, payload in [*hostile, *good, late]:
            tracker.put(key, payload)
        assert eventually(lambda: link.service.poses_dropped == 4, WAIT)
        times = t0 + 0.05 + np.arange(10) / 10  # each between two of the tracker's poses
        for first, at in ((0, times), (10, np.full(3, t0 + 1.5))):  # the newest is 0.6 s old
            batch = _batch(
                "r-trk", 0, first, at.shape[0], times=at, poses=np.full((at.shape[0], 3), 0.5)
            )
            assert _ask(robot, traces_key("r-trk"), encode_trace(batch)).ok is not None
        with link.service.sessions() as db:
            rows = db.scalars(
                select(TraceRow).where(TraceRow.robot_id == "r-trk").order_by(TraceRow.first)
            ).all()
        token.undeclare()  # type: ignore[no-untyped-call]
    assert [r.pose_source for r in rows] == ["tracker", "odometry"]
    assert rows[0].poses is not None and rows[1].poses is not None
    tracked = np.frombuffer(rows[0].poses, "<f8").reshape(-1, 3)
    assert tracked[:, 0].tolist() == list(range(10))
    assert (np.frombuffer(rows[1].poses, "<f8") == 0.5).all()


def test_a_stuck_request_carries_its_nonce() -> None:
    request = StuckRequest(robot="r", sha256=None, reason="x", step=3, nonce="a" * 32)
    assert decode_message(encode_message(request)) == request
    for nonce in ("", "not hex", "a" * 31):
        with pytest.raises(ValueError):
            StuckRequest(robot="r", sha256=None, reason="x", step=3, nonce=nonce)


def test_a_trace_row_keeps_only_the_controllers_its_samples_name(tmp_path: Path) -> None:
    """A batch may list up to MAX_TRACE_SAMPLES controllers whatever its samples: one sample
    listing 10,000 would store 680 kB a sample (55 GB an hour within the sample budget). The
    row keeps the one its samples name, renumbered, and reads back as sent."""
    import hashlib
    import json

    from server.core.db import session_factory
    from server.robots.traces import TraceIngest

    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    ingest = TraceIngest(session_factory(engine), RobotSettings(), lambda robot: True)
    shas = tuple(hashlib.sha256(str(i).encode()).hexdigest() for i in range(10_000))
    named = np.array([-1, 7_321, 7_321, -1], dtype=np.int32)  # escape, a controller, escape
    batch = TraceBatch(
        robot="bot1",
        boot=0,
        controllers=shas,
        status=RobotStatus(state="running", steps=4, sha256=shas[7_321], serial_ok=True),
        steps=np.arange(4, dtype=np.int64),
        whiskers=np.zeros((4, 5), np.uint8),
        motors=np.full((4, 2), 0.5),
        controller=named,
        fresh=np.zeros(4, np.bool_),
        times=np.full(4, time.time()),
        poses=np.zeros((4, 3)),
        pose_source="odometry",
    )
    assert ingest.store(batch) == (3, 4)
    with session_factory(engine)() as db:
        row = db.scalars(select(TraceRow)).one()
    assert json.loads(row.controllers) == [shas[7_321]]
    stored = np.frombuffer(row.controller, dtype="<i4")
    assert stored.tolist() == [-1, 0, 0, -1]
    assert [json.loads(row.controllers)[i] if i >= 0 else None for i in stored] == [
        shas[i] if i >= 0 else None for i in named
    ]
    engine.dispose()


def test_samples_of_a_boot_no_longer_cached_are_still_known_as_stored(tmp_path: Path) -> None:
    """A robot may start a new boot with every sample, so only its newest boots stay in
    memory; a boot read back from the database still knows which of its samples it has."""
    from server.core.db import session_factory
    from server.robots.traces import BOOTS_CACHED, TraceIngest

    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    ingest = TraceIngest(session_factory(engine), RobotSettings(), lambda robot: True)

    def batch(boot: int) -> TraceBatch:
        return TraceBatch(
            robot="bot1",
            boot=boot,
            controllers=(),
            status=RobotStatus(state="escaping", steps=2, sha256=None, serial_ok=True),
            steps=np.arange(2, dtype=np.int64),
            whiskers=np.zeros((2, 5), np.uint8),
            motors=np.zeros((2, 2)),
            controller=np.full(2, -1, np.int32),
            fresh=np.zeros(2, np.bool_),
            times=np.full(2, time.time()),
            poses=np.zeros((2, 3)),
            pose_source="odometry",
        )

    for boot in range(BOOTS_CACHED + 3):
        assert ingest.store(batch(boot)) == (1, 2)
    assert ingest.store(batch(0)) == (1, 0)  # boot 0 again (a lost ack): nothing added
    engine.dispose()
