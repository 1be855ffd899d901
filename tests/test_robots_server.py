"""The server's robot side: real uvicorn, real SQLite, real zenoh on 127.0.0.1, agents as threads
over BasicX emulator ptys. Pushes, rejections, stuck replacement, server restart, replay."""

from __future__ import annotations

import json
import queue
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st
from sqlalchemy import select
from typer.testing import CliRunner

from colony.cli import app as cli
from evorobotics import network
from evorobotics.document import ControllerDocument, controller_sha256
from evorobotics.evolution import validate
from robot_agent.stuck import StuckConfig
from schemas.network import NetworkSpec
from schemas.robots import (
    ESCAPE,
    ControllerPush,
    PushAck,
    RobotStatus,
    StuckEventOut,
    TraceBatch,
    ack_key,
    command_key,
    decode_message,
    decode_trace,
    encode_trace,
)
from schemas.robots import encode_message as encode_robot_message
from schemas.run import RunConfig
from schemas.wire import WireError
from schemas.world import World
from server.core.models import Robot, Run
from server.core.settings import Settings
from server.robots.settings import RobotSettings
from server.robots.store import FieldStatsRow, StuckEventRow, TraceRow, trace_checksum
from server.robots.traces import replay_trace
from server.runs import crud
from tests.helpers import (
    QUICK,
    WAIT,
    Colony,
    Link,
    client_config,
    completed_run,
    constant_drive,
    eventually,
    free_port,
    online,
    random_controller,
    robot_link,
    save,
    serving,
    virtual_robot,
)


@pytest.fixture(scope="module")
def colony(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Colony]:
    tmp = tmp_path_factory.mktemp("robots")
    db_url = f"sqlite:///{tmp / 'colony.db'}"
    # zenoh off: each test opens its own router (to kill and restart it) with a RobotService
    settings = Settings(db_url=db_url, port=free_port(), executors=1, zenoh=False)
    with serving(settings) as (url, app):
        yield Colony(url, db_url, completed_run(url, QUICK), app, tmp)


def test_push_ack_run_replay_and_tamper(colony: Colony, tmp_path: Path) -> None:
    with (
        robot_link(colony) as link,
        virtual_robot("r-push", link, tmp_path) as (agent, _),
        httpx.Client(base_url=colony.url, timeout=30) as client,
    ):
        assert eventually(lambda: online(client, "r-push"))
        assert "r-push" in [r["id"] for r in client.get("/api/robots").json()]
        listed = client.get("/api/robots").json()
        in_colony = client.get("/api/colony").json()["robots"]  # the same view of robots
        assert [sorted(r) for r in in_colony] == [sorted(r) for r in listed]
        assert [(r["id"], r["online"]) for r in in_colony] == [
            (r["id"], r["online"]) for r in listed
        ]
        pushed = client.post(
            "/api/robots/r-push/controller", json={"run_id": colony.run_id, "rank": 1}
        )
        assert pushed.status_code == 200, pushed.text
        body = pushed.json()
        assert body["acknowledged"] and body["accepted"]
        assert agent.controller is not None and body["sha256"] == agent.controller.sha256
        assert agent.controller.provenance["rank"] == 1
        assert agent.wait_for(lambda: agent.delivered >= 40, WAIT)

        detail = client.get("/api/robots/r-push").json()
        assert detail["controller_sha256"] == body["sha256"]
        assert (detail["controller_run"], detail["controller_rank"]) == (colony.run_id, 1)
        assert detail["steps"] > 0 and len(detail["whiskers"]) == 5
        assert detail["link"]["zenoh"] == "online" and detail["link"]["serial_ok"]
        traces = client.get("/api/robots/r-push/traces", params={"limit": 20}).json()
        assert len(traces["samples"]) == 20
        assert traces["samples"][-1]["controller_sha256"] == body["sha256"]
        stats = link.service.field_stats(body["sha256"])
        assert stats is not None and stats.robot_hours > 0 and stats.stuck_events == 0

        replay = client.get("/api/robots/r-push/replay").json()
        assert replay["identical"] and replay["checked"] >= 30 and replay["segments"] >= 1
        run = CliRunner().invoke(cli, ["replay", "r-push", "--server", colony.url])
        assert run.exit_code == 0 and "identical" in run.output

        with link.service.sessions.begin() as db:  # flip the last bit of one sent command
            row = db.scalars(
                select(TraceRow).where(TraceRow.robot_id == "r-push").order_by(TraceRow.first)
            ).all()[-1]
            motors = np.frombuffer(row.motors, "<f8").copy()
            motors[-1] = np.nextafter(motors[-1], 2.0)
            row.motors = motors.tobytes()
        damaged = client.get("/api/robots/r-push/replay")  # the bytes no longer match
        assert damaged.status_code == 500
        assert damaged.json()["detail"] == (
            f"robot r-push boot {row.boot} trace batch from step {row.first}: stored bytes are "
            "damaged (checksum mismatch)"
        )
        with link.service.sessions.begin() as db:  # a command the robot really sent, say
            again = db.get(TraceRow, (row.robot_id, row.boot, row.first))
            assert again is not None
            again.checksum = trace_checksum(again)
        tampered = client.get("/api/robots/r-push/replay").json()
        assert not tampered["identical"] and tampered["mismatches"] == 1
        assert tampered["first_mismatch"]["step"] == row.last
        run = CliRunner().invoke(cli, ["replay", "r-push", "--server", colony.url])
        assert run.exit_code == 1 and "NOT identical" in run.output


def test_bad_push_is_rejected_and_the_old_controller_kept(colony: Colony, tmp_path: Path) -> None:
    good = random_controller(11)
    save(tmp_path, good)
    with robot_link(colony) as link, virtual_robot("r-bad", link, tmp_path) as (agent, _):
        assert agent.connected.wait(WAIT)
        acks: queue.SimpleQueue[PushAck] = queue.SimpleQueue()

        def on_ack(sample: zenoh.Sample) -> None:
            message = decode_message(sample.payload.to_bytes())
            if isinstance(message, PushAck):
                acks.put(message)

        subscriber = link.router.declare_subscriber(ack_key("r-bad"), on_ack)
        try:
            assert eventually(lambda: link.service.is_online("r-bad"))
            other = random_controller(12)
            forged = other.to_dict()
            forged["sha256"] = good.sha256  # claims another id: tampered in transit
            spec4 = NetworkSpec(inputs=4, hidden=(3,), delays=0, recurrence=0)
            wrong = ControllerDocument(spec4, np.zeros(spec4.weight_count))
            for document, sha, reason in (
                (json.dumps(forged), good.sha256, "sha256 mismatch"),
                (wrong.to_json(), wrong.sha256, "5 inputs and 2 outputs"),
                ("{not json", good.sha256, "invalid JSON"),
            ):
                push_id = uuid.uuid4().hex
                push = ControllerPush(push_id=push_id, sha256=sha, document=document)
                link.router.put(command_key("r-bad"), encode_robot_message(push))
                ack = acks.get(timeout=WAIT)
                assert ack.push_id == push_id and not ack.accepted
                assert reason in ack.reason and ack.sha256 == good.sha256
            steps = agent.steps
            assert agent.wait_for(lambda: agent.steps >= steps + 5, WAIT)
            assert agent.controller == good and agent.state == "running"
        finally:
            subscriber.undeclare()  # type: ignore[no-untyped-call]


def test_stuck_robot_gets_a_replacement_from_the_run(colony: Colony, tmp_path: Path) -> None:
    """Pushed a controller that drives into the first wall, the robot gets the run's champion;
    the stuck event counts in the pushed controller's field statistics (the server gave it)."""
    wall = constant_drive(0.9, 0.9, NetworkSpec())  # paper-best shape, drives straight on
    with robot_link(colony) as link:
        with link.service.sessions.begin() as db:
            crud.put_controller(
                db,
                sha256=wall.sha256,
                document=wall.to_json(),
                run_id=colony.run_id,
                generation=None,
                fitness=None,
            )
            run = db.get(Run, colony.run_id)
            assert run is not None
            champion = crud.champion(db, run=run)
            assert champion is not None  # the completed run's, validated and tested
            best = ControllerDocument.from_json(champion.document)
        stuck = StuckConfig(contact_steps=5)
        with virtual_robot("r-stuck", link, tmp_path, stuck=stuck) as (agent, _):
            assert eventually(lambda: link.service.is_online("r-stuck"))
            assert link.service.push("r-stuck", sha256=wall.sha256).accepted
            assert agent.wait_for(
                lambda: agent.controller is not None and agent.controller.sha256 != wall.sha256,
                WAIT,
            )
            assert agent.controller == best
            assert agent.stuck_events >= 1
        with link.service.sessions() as db:
            event = db.scalars(
                select(StuckEventRow).where(StuckEventRow.robot_id == "r-stuck")
            ).first()
            assert event is not None and event.controller_sha256 == wall.sha256
            assert event.replacement_sha256 == best.sha256
            stats = db.get(FieldStatsRow, wall.sha256)
            assert stats is not None and stats.stuck_events >= 1
        detail = link.service.robot("r-stuck")
        assert detail.stuck_events >= 1
        assert (tmp_path / "controller.json").read_text() == best.to_json()  # resumes with it


def test_a_replacement_that_ran_unstuck_hands_the_robot_back_to_its_home_controller(
    colony: Colony, tmp_path: Path
) -> None:
    wall = constant_drive(0.9, 0.9, NetworkSpec())  # drives into the first wall it meets
    save(tmp_path, wall)
    with robot_link(colony) as link:
        with link.service.sessions.begin() as db:
            crud.put_controller(
                db,
                sha256=wall.sha256,
                document=wall.to_json(),
                run_id=colony.run_id,
                generation=None,
                fitness=None,
            )
        stuck = StuckConfig(contact_steps=5)
        with virtual_robot(
            "r-home", link, tmp_path, stuck=stuck, period=0.02, return_after_steps=10
        ) as (agent, _):
            assert agent.wait_for(
                lambda: agent.controller is not None and agent.controller.sha256 != wall.sha256,
                WAIT,
            )
            # home again with no push in between: the server never sends it (it failed here)
            assert agent.wait_for(
                lambda: agent.controller is not None and agent.controller.sha256 == wall.sha256,
                WAIT,
            )


def test_server_restart_buffered_traces_arrive(colony: Colony, tmp_path: Path) -> None:
    doc = random_controller(13, NetworkSpec())
    save(tmp_path, doc)
    port = free_port()
    with robot_link(colony, port) as link, virtual_robot("r-restart", link, tmp_path) as pair:
        with link.service.sessions.begin() as db:  # known to the server: replayable
            crud.put_controller(
                db,
                sha256=doc.sha256,
                document=doc.to_json(),
                run_id=None,
                generation=None,
                fitness=None,
            )
        agent, _ = pair
        assert agent.wait_for(lambda: agent.delivered >= 20, WAIT)
        # the server goes away; the robot keeps running and buffering
        link.service.close()
        link.router.close()  # type: ignore[no-untyped-call]
        offline_from = agent.steps
        assert agent.wait_for(lambda: agent.steps >= offline_from + 30, WAIT)
        assert agent.buffered() >= 20
        with robot_link(colony, port) as again:
            assert eventually(lambda: again.service.is_online("r-restart"))
            assert agent.wait_for(lambda: agent.buffered() < 15 and agent.steps > 0, WAIT)
            last = agent.steps - agent.buffered() - 1
            with again.service.sessions() as db:
                rows = db.scalars(
                    select(TraceRow)
                    .where(TraceRow.robot_id == "r-restart", TraceRow.boot == agent.boot)
                    .order_by(TraceRow.first)
                ).all()
            steps = np.concatenate([np.frombuffer(r.steps, "<i8") for r in rows])
            assert steps[0] == 0 and steps[-1] >= last
            assert np.array_equal(steps, np.arange(steps[-1] + 1))  # no sample lost
            assert agent.dropped == 0
            assert again.service.replay("r-restart").identical


def test_stop_and_http_errors(colony: Colony, tmp_path: Path) -> None:
    save(tmp_path, constant_drive(0.3, 0.3))
    with (
        robot_link(colony) as link,
        httpx.Client(base_url=colony.url, timeout=30) as client,
    ):
        with virtual_robot("r-stop", link, tmp_path) as (agent, emulator):
            assert eventually(lambda: online(client, "r-stop"))
            stopped = client.post("/api/robots/r-stop/stop").json()
            assert stopped["acknowledged"] and stopped["accepted"]
            assert agent.state == "stopped"
            assert emulator.wait_steps(emulator.steps + 2, WAIT)
            assert emulator.motors == (0.0, 0.0)
            both = {"sha256": "a" * 64, "run_id": colony.run_id}
            for body in ({}, both, {"run_id": -1}, {"sha256": "xyz"}):
                response = client.post("/api/robots/r-stop/controller", json=body)
                assert response.status_code == 422, body
                assert response.json()["detail"]
            missing = client.post("/api/robots/r-stop/controller", json={"sha256": "b" * 64})
            assert missing.status_code == 404 and "b" * 64 in missing.json()["detail"]
            no_rank = {"run_id": colony.run_id, "rank": 99}
            assert client.post("/api/robots/r-stop/controller", json=no_rank).status_code == 404
        assert eventually(lambda: not online(client, "r-stop"), 10)
        offline = client.post("/api/robots/r-stop/controller", json={"run_id": colony.run_id})
        assert offline.status_code == 409 and "offline" in offline.json()["detail"]
        for path in ("", "/traces", "/replay"):
            response = client.get(f"/api/robots/nobody{path}")
            assert response.status_code == 404 and "nobody" in response.json()["detail"]
        assert client.post("/api/robots/nobody/stop").status_code == 404


# ---------------------------------------------------------------------------- properties


def _trace(
    doc: ControllerDocument, whiskers: np.ndarray, escape_at: int | None
) -> tuple[TraceRow, np.ndarray]:
    """A stored batch as an agent produces it: the controller from fresh state, optionally an
    escape sample and a fresh restart at `escape_at`; returns it and its motors."""
    state = network.reset(doc.spec, 1)
    motors = np.empty((whiskers.shape[0], 2))
    controller = np.zeros(whiskers.shape[0], dtype=np.int32)
    fresh = np.zeros(whiskers.shape[0], dtype=bool)
    fresh[0] = True
    for k in range(whiskers.shape[0]):
        if k == escape_at:
            motors[k], controller[k] = (-0.6, -0.6), ESCAPE
            continue
        if escape_at is not None and k == escape_at + 1:
            state, fresh[k] = network.reset(doc.spec, 1), True
        out, state = network.step(doc.spec, doc.weights[None, :], whiskers[k : k + 1] * 1.0, state)
        motors[k] = network.motor_commands(doc.spec, out)[0]
    n = whiskers.shape[0]
    row = TraceRow(
        robot_id="p",
        boot=0,
        first=0,
        last=n - 1,
        count=n,
        controllers=json.dumps([doc.sha256]),
        steps=np.arange(n, dtype="<i8").tobytes(),
        whiskers=whiskers.astype("|u1").tobytes(),
        motors=motors.astype("<f8").tobytes(),
        controller=controller.astype("<i4").tobytes(),
        fresh=fresh.tobytes(),
    )
    return row, motors


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    n=st.integers(2, 60),
    escape=st.booleans(),
    flip=st.integers(0, 10_000),
)
def test_replay_is_identical_and_detects_any_single_flipped_bit(
    seed: int, n: int, escape: bool, flip: int
) -> None:
    rng = np.random.default_rng(seed)
    doc = random_controller(seed % 1000, NetworkSpec())
    whiskers = (rng.random((n, 5)) < 0.3).astype(np.uint8)
    escape_at = int(rng.integers(1, n - 1)) if escape and n >= 3 else None
    row, motors = _trace(doc, whiskers, escape_at)
    report = replay_trace("p", [row], {doc.sha256: doc})
    assert report.identical and report.mismatches == 0
    assert report.checked == n - (escape_at is not None)
    assert report.segments == 1 + (escape_at is not None)  # fresh again after the escape
    driven = [k for k in range(n) if k != escape_at]
    k = driven[flip % len(driven)]
    tampered = motors.copy()
    bits = tampered.view("<u8")
    bits[k, flip % 2] ^= np.uint64(1) << np.uint64(flip % 52)
    row.motors = tampered.astype("<f8").tobytes()
    bad = replay_trace("p", [row], {doc.sha256: doc})
    assert not bad.identical and bad.mismatches == 1
    assert bad.first_mismatch is not None and bad.first_mismatch["step"] == k


@settings(max_examples=50, deadline=None)
@given(n=st.integers(1, 50), seed=st.integers(0, 2**31), boot=st.integers(0, 1000))
def test_trace_batches_round_trip_bit_for_bit(n: int, seed: int, boot: int) -> None:
    rng = np.random.default_rng(seed)
    batch = TraceBatch(
        robot="r-1",
        boot=boot,
        controllers=("a" * 64, "b" * 64),
        status=RobotStatus(state="running", steps=n, sha256=None, serial_ok=True),
        steps=np.cumsum(rng.integers(1, 3, n)).astype(np.int64),
        whiskers=rng.integers(0, 2, (n, 5)).astype(np.uint8),
        motors=rng.uniform(-1, 1, (n, 2)),
        controller=rng.integers(-1, 2, n).astype(np.int32),
        fresh=rng.random(n) < 0.2,
        times=np.sort(rng.uniform(0, 2e9, n)),
        poses=rng.uniform(-3, 3, (n, 3)),
        pose_source="sim",
    )
    back = decode_trace(encode_trace(batch))
    for name in ("steps", "whiskers", "motors", "controller", "fresh", "times", "poses"):
        assert getattr(back, name).tobytes() == getattr(batch, name).tobytes()
    assert (back.robot, back.boot, back.controllers, back.status) == (
        batch.robot,
        batch.boot,
        batch.controllers,
        batch.status,
    )
    with pytest.raises(WireError):
        decode_trace(encode_trace(batch)[:-1])


def test_archive_policy_replaces_with_an_elite_and_pushes_reach_archive_entries(
    colony: Colony, tmp_path: Path
) -> None:
    """Policy `archive`: a robot stuck with a controller of a map-elites run (not one of its
    elites) gets the run's fittest elite, signed like any replacement; then an operator pushes
    elite 0 of the archive (`elite`), as `GET /api/runs/{id}/archive` lists it."""
    run_id = completed_run(colony.url, {**QUICK, "strategy": "map-elites"})
    archive = httpx.get(f"{colony.url}/api/runs/{run_id}/archive").json()["cells"]
    fittest = max(range(len(archive)), key=lambda k: archive[k]["fitness"])
    wall = constant_drive(0.85, 0.85, NetworkSpec())  # not the stored one of another run
    save(tmp_path, wall)
    with robot_link(colony, settings=RobotSettings(replacement="archive")) as link:
        with link.service.sessions.begin() as db:
            crud.put_controller(
                db,
                sha256=wall.sha256,
                document=wall.to_json(),
                run_id=run_id,
                generation=None,
                fitness=None,
            )
        stuck = StuckConfig(contact_steps=5)
        with virtual_robot("r-elite", link, tmp_path, stuck=stuck) as (agent, _):
            assert agent.wait_for(
                lambda: agent.controller is not None and agent.controller.sha256 != wall.sha256,
                WAIT,
            )
            assert agent.controller is not None
            assert agent.controller.sha256 == archive[fittest]["sha256"]
            with link.service.sessions() as db:
                event = db.scalars(
                    select(StuckEventRow).where(StuckEventRow.robot_id == "r-elite")
                ).first()
                assert event is not None and event.policy == "archive"
                assert event.replacement_sha256 == archive[fittest]["sha256"]
            path = f"{colony.url}/api/robots/r-elite/controller"
            pushed = httpx.post(path, json={"run_id": run_id, "elite": 0}, timeout=WAIT).json()
            assert pushed["accepted"] and pushed["sha256"] == archive[0]["sha256"]
            past = httpx.post(path, json={"run_id": run_id, "elite": len(archive)}, timeout=WAIT)
            assert past.status_code == 404 and f"has {len(archive)} entries" in past.text
            both = httpx.post(path, json={"run_id": run_id, "elite": 0, "rank": 0})
            assert both.status_code == 422 and "at most one of rank, elite or fit" in both.text


def test_calibrate_fits_an_emulated_robots_hidden_physics_from_its_traces(
    colony: Colony, tmp_path: Path
) -> None:
    """Traces with an overhead tracker's poses (the emulator's true ones, published on the
    tracker key; the agent itself has only odometry), `colony robot calibrate` over REST, the
    fit stored with the robot: the hidden whisker ranges and wheel gains within its
    uncertainty."""
    from evorobotics.evaluate import draw_gap

    save(tmp_path, constant_drive(0.8, 0.8, NetworkSpec()))  # ahead until a wall, escape, again
    hidden = draw_gap(5, 0, 1)  # SimBody.create("paper", seed=5): robot 0's gap
    stuck = StuckConfig(contact_steps=2, odometry_window=20)
    with (
        robot_link(colony) as link,
        virtual_robot("r-cal", link, tmp_path, seed=5, tracker=True, stuck=stuck, period=0.005) as (
            agent,
            _,
        ),
    ):
        assert agent.wait_for(lambda: agent.delivered >= 3000, WAIT * 2)
        assert agent.pose_source == "odometry"
        assert httpx.get(f"{colony.url}/api/robots/r-cal/calibration").status_code == 404
        done = CliRunner().invoke(
            cli, ["robot", "calibrate", "r-cal", "--server", colony.url, "--json"]
        )
        assert done.exit_code == 0, done.stderr  # a whisker never at a wall: bounded above
        printed = json.loads(done.stdout)  # the contract: the fit's members on top
        assert {"whisker_range", "motor_gain", "uncertainty", "samples", "residuals"} <= set(
            printed
        ) and printed["robot"] == "r-cal"
        stored = httpx.get(f"{colony.url}/api/robots/r-cal/calibration").json()
        fit = stored["calibration"]
        assert {k: printed[k] for k in fit} == fit
        delivered = agent.delivered
        assert agent.wait_for(lambda: agent.delivered >= delivered + 200, WAIT)
        detail = httpx.get(f"{colony.url}/api/robots/r-cal").json()  # what the Colony page shows
        assert detail["calibration"] == fit
        before, since = detail["before_calibration"], detail["since_calibration"]
        assert before["robot_hours"] >= 3000 * 0.1 / 3600 and since["robot_hours"] > 0
        assert before["stuck_events"] > 0  # ahead until a wall, again and again
        bad = {**fit, "motor_gain": [0.0, 1.0]}
        refused = httpx.post(f"{colony.url}/api/robots/r-cal/calibration", json=bad)
        assert refused.status_code == 422 and "motor_gain" in refused.text
    assert stored["calibration"] == fit and stored["robot"] == "r-cal"
    # the emulator steps in real time, not in lockstep with the agent: a physics step may fall
    # between a sample's whisker and pose reads, or take the previous command (the fit drops
    # such steps as outliers)
    assert fit["motor_gain"] == pytest.approx(hidden.motor_gain[0].tolist(), abs=0.005)
    for got, err, true in zip(
        fit["whisker_range"], fit["uncertainty"]["whisker_range"], hidden.whisker_range[0],
        strict=True,
    ):  # fmt: skip
        assert abs(got - true) <= err + 0.002


def test_evaluate_in_a_robots_calibrated_world(colony: Colony, tmp_path: Path) -> None:
    """`colony evaluate --robot ID` runs the controller with the robot's stored whiskers and
    gains; an uncalibrated robot is one line and exit 2."""
    from colony.documents import robot_world
    from evorobotics.explore import explore
    from schemas.world import World

    doc = random_controller(21, NetworkSpec())
    path = tmp_path / "c.json"
    path.write_text(doc.to_json())
    fit = {
        "whisker_range": [0.03, 0.04, 0.05, 0.06, 0.07],
        "motor_gain": [0.9, 1.1],
        "uncertainty": {"whisker_range": [0.001] * 5, "motor_gain": [0.001, 0.001]},
        "samples": 500,
        "residuals": {"moving_steps": 400, "pose_rms_m": 0.0, "whisker_disagreements": [0] * 5},
    }
    with robot_link(colony) as link, virtual_robot("r-eval", link, tmp_path):
        assert eventually(lambda: link.service.is_online("r-eval"))
        args = ["evaluate", str(path), "--poses", "20", "--steps", "60", "--server", colony.url]
        done = CliRunner().invoke(cli, [*args, "--robot", "r-eval", "--json"])
        assert done.exit_code == 2 and "no calibration" in done.stderr
        posted = httpx.post(f"{colony.url}/api/robots/r-eval/calibration", json=fit)
        assert posted.status_code == 200, posted.text
        done = CliRunner().invoke(cli, [*args, "--robot", "r-eval", "--json"])
        assert done.exit_code == 0, done.stderr
        world = robot_world(colony.url, "r-eval", None)
    assert world.whisker_range == (0.03, 0.04, 0.05, 0.06, 0.07) and world.motor_gain == (0.9, 1.1)
    want = explore(doc.spec, doc.weights, poses=20, steps=60, world=world)
    got = json.loads(done.stdout)
    assert got["world"] == "robot:r-eval" and got["roaming_fraction"] == want.roaming
    assert want != explore(doc.spec, doc.weights, poses=20, steps=60, world=World())


class PinnedBody:
    """A robot held in place with every whisker clear of the wall, its wheels free to turn:
    neither whiskers nor commands can tell it from one that drives."""

    dt = 0.1

    def step(self, left: float, right: float) -> None:
        pass

    def whiskers(self) -> tuple[bool, ...]:
        return (False,) * 5

    def position(self) -> tuple[float, float, float]:
        return (1.0, 1.0, 0.5)


def test_a_tracker_lets_the_agent_see_a_robot_pinned_with_its_whiskers_clear(
    colony: Colony, tmp_path: Path
) -> None:
    """Issue 37, stuck recall: a body pinned with its whiskers clear while its controller
    drives forward raises no alarm from whiskers and commands; once an overhead tracker
    publishes its poses the agent sees it stay put and asks for another controller."""
    from robot_agent.agent import Agent, AgentSettings
    from robot_agent.driver import BasicXDriver
    from robot_agent.emulator import BasicXEmulator, FirmwareConfig
    from robot_agent.tracker import EmulatedTracker

    save(tmp_path, constant_drive(0.8, 0.8, NetworkSpec()))
    with (
        robot_link(colony) as link,
        BasicXEmulator(PinnedBody(), FirmwareConfig(pose_request=False)) as emulator,
        BasicXDriver.open(emulator.port_path) as driver,
        Agent(
            AgentSettings(
                robot_id="r-pin",
                connect=(link.endpoint,),
                state_dir=tmp_path,
                request_timeout=1.0,
                period=0.02,
            ),
            driver,
        ) as agent,
        zenoh.open(client_config(link.port)) as tracker_session,
    ):
        assert agent.wait_for(lambda: agent.steps >= 300, WAIT)  # 6 s driving "forward"
        assert agent.stuck_events == 0
        with EmulatedTracker(tracker_session, "r-pin", emulator):
            assert agent.wait_for(lambda: agent.stuck_events >= 1, WAIT)

        def recorded() -> list[str]:
            return [e.reason for e in link.service.stuck_events("r-pin").events]

        assert eventually(lambda: recorded() != [], WAIT)
    assert recorded()[0] == "tracked-still"


def test_a_run_for_the_colony_trains_on_the_calibrated_robots(tmp_path: Path) -> None:
    """Issue 37: `colony run start --for-colony` (`reality_gap: "colony"`): refused while no
    robot is calibrated; then the server stores the calibrated robots in the run's config,
    and the run is `evolve` of that config."""
    from evorobotics.evolution import evolve
    from schemas.run import RunConfig

    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{free_port()}"],
        workers=0,
        executors=1,
    )
    fit = {
        "whisker_range": [0.03, 0.04, 0.05, 0.06, 0.07],
        "motor_gain": [0.9, 1.1],
        "uncertainty": {"whisker_range": [0.002] * 5, "motor_gain": [0.01, 0.01]},
        "samples": 500,
        "residuals": {"moving_steps": 400, "pose_rms_m": 0.0, "whisker_disagreements": [0] * 5},
    }
    args = ["run", "start", "--for-colony", "--population", "8", "--generations", "3"]
    args += ["--steps", "20", "--follow", "--json"]
    with serving(settings) as (url, app):
        refused = CliRunner().invoke(cli, [*args, "--server", url])
        assert refused.exit_code == 1 and "no robot is calibrated" in refused.output
        with app.state.robots.sessions.begin() as db:
            db.add(Robot(id="r-col", status="offline"))
        assert httpx.post(f"{url}/api/robots/r-col/calibration", json=fit).status_code == 200
        done = CliRunner().invoke(cli, [*args, "--server", url])
        assert done.exit_code == 0, done.output
        run = httpx.get(f"{url}/api/runs").json()[0]
    config = RunConfig.model_validate(run["config"])
    (robot,) = config.world.gap_robots
    assert robot.robot == "r-col" and robot.whisker_range == (0.03, 0.04, 0.05, 0.06, 0.07)
    assert robot.motor_gain_uncertainty == (0.01, 0.01)
    assert run["best_fitness"] == float(evolve(config).fitness.max())


def test_a_robot_flooding_stuck_requests_is_rate_limited_and_its_ledger_trimmed(
    colony: Colony,
) -> None:
    """Issue 38, attack 5: a robot credential sent 87 signed, fsynced stuck requests a second,
    and the events were never trimmed. Beyond a burst, requests are refused unrecorded; the
    ledger keeps the newest `stuck_retention` events."""
    from schemas.robots import StuckRequest, replace_key

    settings = RobotSettings(push_timeout=5.0, stuck_burst=6, stuck_per_s=0.5, stuck_retention=4)
    with robot_link(colony, settings=settings) as link:
        with link.service.sessions.begin() as db:  # known to the colony, as its agent made it
            db.add(Robot(id="r-flood", status="online"))
        session = zenoh.open(client_config(link.port))
        try:
            answers = []
            for k in range(12):
                request = StuckRequest(
                    robot="r-flood", sha256=None, reason="x", step=k, nonce=uuid.uuid4().hex
                )
                replies = list(
                    session.get(
                        replace_key("r-flood"), payload=encode_robot_message(request), timeout=5
                    )
                )
                assert len(replies) == 1
                answers.append(replies[0].ok is not None)
        finally:
            session.close()  # type: ignore[no-untyped-call]
        allowed = sum(answers)
        assert answers[:6] == [True] * 6 and not any(answers[7:])  # 0.5 a second refills slowly
        ledger = link.service.stuck_events("r-flood").events
        assert [e.step for e in ledger] == list(range(allowed - 4, allowed))


RANKED_RUN = {
    "population": 16,
    "generations": 6,
    "steps": 200,
    "job_size": 8,
    "validation": {"poses": 20, "steps": 400, "candidates": 16, "test_poses": 0},
}
"""A run of a second whose candidates the server's validation tells apart."""


def latest_candidates(link: Link, run_id: int) -> tuple[Run, RunConfig, np.ndarray]:
    """A completed run's row (with its champion), config, and latest generation's genomes in
    training-rank order, as the server stored them."""
    with link.service.sessions() as db:
        run = db.get(Run, run_id)
        assert run is not None and run.champion_sha256 is not None
        latest = crud.latest_generation(db, run_id=run_id)
        assert latest is not None
        _, genomes = crud.ranked(db, run_id=run_id, generation=latest.generation)
    return run, RunConfig.model_validate_json(run.config), genomes


def validated_order(config: RunConfig, genomes: np.ndarray, world: World) -> dict[str, Any]:
    """Each candidate's (roaming, mean Eq 12) on the run's validation poses in `world`."""
    there = config.model_copy(update={"world": world, "reality_gap": "off"})
    scored = validate(there, genomes)
    return {
        controller_sha256(config.network_spec, g): (float(r), float(s))
        for g, r, s in zip(genomes, scored.roaming, scored.score, strict=True)
    }


def test_rank_policy_past_the_champion_serves_the_servers_own_validated_order(
    colony: Colony,
) -> None:
    """Issue 38, attack 3: a genome crowned by forged training fitness became training rank 0
    and `rank` served it. Once a robot failed with the champion, `rank` serves the candidate
    the server's own validation ranks first, never a training rank as claimed."""
    from schemas.robots import StuckRequest, replace_key

    run_id = completed_run(colony.url, RANKED_RUN)
    with robot_link(colony, settings=RobotSettings(push_timeout=5.0, replacement="rank")) as link:
        with link.service.sessions.begin() as db:
            db.add(Robot(id="r-rank", status="online"))
        run, config, genomes = latest_candidates(link, run_id)
        key = validated_order(config, genomes, config.world)
        session = zenoh.open(client_config(link.port))

        def stuck_with_the_champion() -> bool:
            request = StuckRequest(
                robot="r-rank", sha256=run.champion_sha256, reason="x", step=1,
                nonce=uuid.uuid4().hex,
            )  # fmt: skip
            list(session.get(replace_key("r-rank"), payload=encode_robot_message(request)))
            answer = link.service.stuck_events("r-rank").events[-1].answer or ""
            return "validation trials" in answer

        try:
            assert eventually(stuck_with_the_champion, WAIT)
        finally:
            session.close()  # type: ignore[no-untyped-call]
        events = link.service.stuck_events("r-rank").events
    assert all(
        e.replacement_sha256 is None and "being validated" in (e.answer or "") for e in events[:-1]
    )
    served = events[-1].replacement_sha256
    assert served is not None and served != run.champion_sha256
    others = {sha: k for sha, k in key.items() if sha != run.champion_sha256}
    assert key[served] == max(others.values()), events[-1].answer


def test_fit_policy_serves_the_candidate_that_roams_most_in_the_robots_calibrated_world(
    colony: Colony, tmp_path: Path
) -> None:
    """Policy `fit`: uncalibrated, a stuck robot gets the `rank` choice, saying why; once
    calibrated, `colony robot push --run --fit` and its next stuck request get the run's
    candidate that roams most on the validation poses in the robot's calibrated world (here
    not the champion, which was chosen in the nominal world)."""
    from schemas.robots import RobotCalibration

    fit = {
        "whisker_range": [0.025, 0.03, 0.03, 0.03, 0.025],  # short whiskers, slow right wheel
        "motor_gain": [1.0, 0.85],
        "uncertainty": {"whisker_range": [0.001] * 5, "motor_gain": [0.001, 0.001]},
        "samples": 500,
        "residuals": {"moving_steps": 400, "pose_rms_m": 0.0, "whisker_disagreements": [0] * 5},
    }
    run_id = completed_run(colony.url, RANKED_RUN)
    wall = constant_drive(0.87, 0.87, NetworkSpec())  # stored by no other test, so of this run
    save(tmp_path, wall)
    stuck = StuckConfig(contact_steps=5)
    with robot_link(colony, settings=RobotSettings(push_timeout=5.0, replacement="fit")) as link:
        run, config, genomes = latest_candidates(link, run_id)
        with link.service.sessions.begin() as db:
            crud.put_controller(
                db,
                sha256=wall.sha256,
                document=wall.to_json(),
                run_id=run_id,
                generation=None,
                fitness=None,
            )
        key = validated_order(
            config, genomes, RobotCalibration.model_validate(fit).world(config.world)
        )
        with virtual_robot("r-fit", link, tmp_path, stuck=stuck):
            assert eventually(lambda: link.service.is_online("r-fit"))
            assert eventually(lambda: bool(link.service.stuck_events("r-fit").events), WAIT)
            first = link.service.stuck_events("r-fit").events[0]
            assert first.policy == "fit" and first.replacement_sha256 == run.champion_sha256
            assert first.answer is not None and "has no calibration" in first.answer
            assert "; the validated champion of run" in first.answer

            push = ["robot", "push", "r-fit", "--run", str(run_id), "--fit"]
            refused = CliRunner().invoke(cli, [*push, "--server", colony.url])
            assert refused.exit_code != 0 and "has no calibration" in refused.output
            posted = httpx.post(f"{colony.url}/api/robots/r-fit/calibration", json=fit)
            assert posted.status_code == 200, posted.text
            done = CliRunner().invoke(cli, [*push, "--server", colony.url, "--json"])
            assert done.exit_code == 0, done.output
            pushed = json.loads(done.stdout)["sha256"]
            assert key[pushed] == max(key.values()) and pushed != run.champion_sha256

            pushed_wall = httpx.post(
                f"{colony.url}/api/robots/r-fit/controller", json={"sha256": wall.sha256},
                timeout=WAIT,
            ).json()  # fmt: skip
            assert pushed_wall["accepted"]
            seen = len(link.service.stuck_events("r-fit").events)

            def stuck_with_wall() -> list[StuckEventOut]:
                events = link.service.stuck_events("r-fit").events[seen:]
                return [e for e in events if e.controller_sha256 == wall.sha256]

            assert eventually(lambda: bool(stuck_with_wall()), WAIT)
        events = link.service.stuck_events("r-fit").events
    event = stuck_with_wall()[0]
    before = [e.controller_sha256 for e in events if e.id <= event.id][-5:]
    allowed = {sha: k for sha, k in key.items() if sha not in before}
    assert event.answer is not None and "calibrated world" in event.answer, event.answer
    assert event.replacement_sha256 is not None
    assert key[event.replacement_sha256] == max(allowed.values())


def test_the_field_loop_end_to_end(colony: Colony, tmp_path: Path) -> None:
    """Issue 37, done when: an emulated robot with hidden physics, traced with an overhead
    tracker's poses through zenoh; `colony robot calibrate` fits them; `colony robot push
    --fit` sends the run's candidate that roams most in the fitted world; the field ledger
    and the controller's field statistics show it running there."""
    from evorobotics.evaluate import draw_gap
    from schemas.robots import RobotCalibration

    run_id = completed_run(colony.url, RANKED_RUN)
    driver = constant_drive(0.8, 0.8, NetworkSpec())  # ahead until a wall, escape, again
    save(tmp_path, driver)
    hidden = draw_gap(5, 0, 1)  # SimBody.create("paper", seed=5): robot 0's gap
    stuck = StuckConfig(contact_steps=2, odometry_window=20)
    with (
        robot_link(colony, settings=RobotSettings(push_timeout=5.0, replacement="off")) as link,
        virtual_robot(
            "r-loop", link, tmp_path, seed=5, tracker=True, stuck=stuck, period=0.005
        ) as (agent, _),
    ):
        assert agent.wait_for(lambda: agent.delivered >= 3000, WAIT * 2)
        calibrated = CliRunner().invoke(
            cli, ["robot", "calibrate", "r-loop", "--server", colony.url, "--json"]
        )
        assert calibrated.exit_code == 0, calibrated.stderr
        printed = json.loads(calibrated.stdout)
        fit = RobotCalibration.model_validate(
            {k: printed[k] for k in RobotCalibration.model_fields}
        )
        assert np.allclose(fit.motor_gain, hidden.motor_gain[0], atol=0.005)
        _, config, genomes = latest_candidates(link, run_id)
        key = validated_order(config, genomes, fit.world(config.world))
        push = ["robot", "push", "r-loop", "--run", str(run_id), "--fit", "--json"]
        done = CliRunner().invoke(cli, [*push, "--server", colony.url])
        assert done.exit_code == 0, done.output
        pushed = json.loads(done.stdout)["sha256"]
        assert key[pushed] == max(key.values())
        assert agent.controller is not None and agent.controller.sha256 == pushed
        delivered = agent.delivered
        assert agent.wait_for(lambda: agent.delivered >= delivered + 500, WAIT)

        def ran() -> bool:
            stats = link.service.field_stats(pushed)
            return stats is not None and stats.robot_hours > 0

        assert eventually(ran, WAIT)
        args = ["robot", "stuck", "r-loop", "--limit", "1000", "--server", colony.url, "--json"]
        ledger = CliRunner().invoke(cli, args)
        assert ledger.exit_code == 0, ledger.output
        rows = {c["sha256"]: c for c in json.loads(ledger.stdout)["controllers"]}
        assert rows[driver.sha256]["stuck_events"] > 0  # the wall-driver, as the field saw it
        detail = httpx.get(f"{colony.url}/api/robots/r-loop").json()  # the Colony page's
    assert detail["calibration"] == fit.model_dump(mode="json")
    assert detail["before_calibration"]["stuck_events"] > 0  # the wall-driver's
