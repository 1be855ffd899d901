"""Poses in robot traces: the emulator's `P` request reports the simulator's pose bit for bit, a
real BasicX has none and the agent integrates odometry with the simulator's body model, hostile
poses and times are clamped or refused, and GET /api/colony/map draws robots where they are.

Real parts: BasicX emulator ptys, the serial driver, zenoh on 127.0.0.1, uvicorn and SQLite.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import sqlalchemy as sa
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.maze import parse_maze
from robot_agent.driver import BasicXDriver
from robot_agent.emulator import BasicXEmulator
from robot_agent.errors import FirmwareError
from robot_agent.odometry import Odometry
from robot_agent.sim_body import SimBody
from schemas.robots import POSE_LIMIT, RobotStatus, TraceBatch, decode_trace, encode_trace
from schemas.wire import WireError, decode_frame, encode_frame
from schemas.world import World
from server.core.settings import Settings
from server.robots.store import StuckEventRow, TraceRow
from tests.helpers import (
    QUICK,
    WAIT,
    Colony,
    FixedBody,
    completed_run,
    constant_drive,
    eventually,
    free_port,
    online,
    robot_link,
    save,
    serving,
    virtual_robot,
)

OPEN_FLOOR = parse_maze(("." * 100 + "\n") * 100, name="floor")
"""10 m x 10 m without a wall: a simulated robot is never blocked, so it moves as odometry."""


@pytest.fixture(scope="module")
def colony(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Colony]:
    tmp = tmp_path_factory.mktemp("poses")
    db_url = f"sqlite:///{tmp / 'colony.db'}"
    settings = Settings(db_url=db_url, port=free_port(), executors=1, zenoh=False)
    with serving(settings) as (url, app):
        yield Colony(url, db_url, completed_run(url, QUICK), app, tmp)


def test_the_emulator_reports_the_simulators_pose_bit_for_bit() -> None:
    body = SimBody.create("paper", seed=3)
    with BasicXEmulator(body) as emulator, BasicXDriver.open(emulator.port_path) as driver:
        driver.set_motors(0.4, 0.7)
        assert emulator.wait_steps(5, WAIT)
        driver.stop()
        steps = emulator.steps
        assert emulator.wait_steps(steps + 1, WAIT)  # no move is under way any more
        x, y, theta = driver.pose()
        assert (x, y, theta) == tuple(body.pose[0].tolist())
        assert (x, y) != tuple(SimBody.create("paper", seed=3).pose[0, :2].tolist())  # it moved
        with pytest.raises(FirmwareError, match="ERR ARG"):
            driver.request("P 1")


def test_a_firmware_without_a_pose_refuses_the_request() -> None:
    with BasicXEmulator(FixedBody()) as emulator, BasicXDriver.open(emulator.port_path) as driver:
        with pytest.raises(FirmwareError, match="ERR CMD"):
            driver.pose()
        assert driver.whiskers() == FixedBody().bits  # the link is fine


per_mille = st.integers(-1000, 1000).map(lambda v: v / 1000)


@settings(max_examples=40, deadline=None)
@given(
    commands=st.lists(st.tuples(per_mille, per_mille), min_size=1, max_size=60),
    heading=st.floats(-3.14, 3.14),
)
def test_odometry_integrates_commands_as_the_simulator_moves_a_body(
    commands: list[tuple[float, float]], heading: float
) -> None:
    """Nominal wheels on a floor with no wall: the simulated body's pose is exactly odometry's."""
    world = World()
    start = np.array([5.0, 5.0, heading])
    body = SimBody(OPEN_FLOOR, start, params=world)
    odometry = Odometry((5.0, 5.0, heading), world)
    for left, right in commands:
        body.step(left, right)
        odometry.advance(left, right)
        assert not body.blocked
    assert odometry.pose == tuple(body.pose[0].tolist())


def _batch(n: int, poses: np.ndarray, times: np.ndarray | None = None) -> TraceBatch:
    return TraceBatch(
        robot="r-pose",
        boot=0,
        controllers=(),
        status=RobotStatus(state="idle", steps=n, sha256=None, serial_ok=True),
        steps=np.arange(n, dtype=np.int64),
        whiskers=np.zeros((n, 5), np.uint8),
        motors=np.zeros((n, 2)),
        controller=np.full(n, -1, np.int32),
        fresh=np.zeros(n, np.bool_),
        times=np.full(n, time.time()) if times is None else times,
        poses=poses,
        pose_source="odometry",
    )


def _with(payload: bytes, **arrays: np.ndarray) -> bytes:
    header, body = decode_frame(payload)
    body.update(arrays)
    return encode_frame(header, body)


def test_hostile_poses_and_times_are_clamped_or_refused() -> None:
    good = encode_trace(_batch(3, np.zeros((3, 3))))
    far = np.array([[1e9, -1e12, 0.5], [2.0, 3.0, 40.0], [0.0, 0.0, -np.pi]])
    back = decode_trace(_with(good, poses=far))
    assert back.poses[0, :2].tolist() == [POSE_LIMIT, -POSE_LIMIT] and back.poses[0, 2] == 0.5
    assert back.poses[1, :2].tolist() == [2.0, 3.0]
    assert back.poses[1, 2] == pytest.approx(40.0 - 12 * np.pi) and abs(back.poses[1, 2]) <= np.pi
    assert back.poses[2, 2] == -np.pi  # in range: kept bit for bit
    for name, value, reason in [
        ("poses", np.array([[np.nan, 0, 0]] * 3), "poses must be finite"),
        ("poses", np.array([[np.inf, 0, 0]] * 3), "poses must be finite"),
        ("poses", np.zeros((3, 2)), "poses must be float64 (3, 3)"),
        ("times", np.array([3.0, 2.0, 4.0]), "must not decrease"),
        ("times", np.array([np.nan] * 3), "finite Unix seconds"),
        ("times", np.array([-1.0] * 3), "finite Unix seconds"),
    ]:
        with pytest.raises(WireError, match=re.escape(reason)):
            decode_trace(_with(good, **{name: value}))
    header, arrays = decode_frame(good)
    with pytest.raises(WireError, match="protocol 11"):
        decode_trace(encode_frame({**header, "protocol": 11}, arrays))
    with pytest.raises(WireError, match="pose_source"):
        decode_trace(encode_frame({**header, "pose_source": "gps"}, arrays))


@pytest.mark.slow
def test_traces_carry_sim_and_odometry_poses_and_the_map_draws_them(
    colony: Colony, tmp_path: Path
) -> None:
    """An emulated robot's traces carry its simulator's pose; one whose firmware has no pose
    carries odometry from its start pose; a batch from a clock far ahead is refused; the map
    has the maze, the robots where their last sample puts them and their paths."""
    from robot_agent.agent import Agent, AgentSettings

    drive = constant_drive(0.5, 0.5)
    save(tmp_path / "sim", drive)
    save(tmp_path / "odo", drive)
    with (
        robot_link(colony) as link,
        virtual_robot("r-sim", link, tmp_path / "sim") as (sim_agent, emulator),
        BasicXEmulator(FixedBody()) as blind,
        BasicXDriver.open(blind.port_path) as driver,
        Agent(
            AgentSettings(
                robot_id="r-odo",
                connect=(link.endpoint,),
                state_dir=tmp_path / "odo",
                backoff_max=0.5,
                start_pose=(1.0, 2.0, 0.0),
            ),
            driver,
        ) as odo_agent,
        httpx.Client(base_url=colony.url, timeout=30) as client,
    ):
        assert eventually(lambda: online(client, "r-sim") and online(client, "r-odo"))
        assert sim_agent.wait_for(lambda: sim_agent.delivered >= 20, WAIT)
        assert odo_agent.wait_for(lambda: odo_agent.delivered >= 20, WAIT)
        assert sim_agent.pose_source == "sim" and odo_agent.pose_source == "odometry"

        # every sample since it started: its newest 20 may all push against one wall
        sim = client.get("/api/robots/r-sim/traces", params={"limit": 1000}).json()["samples"]
        assert {s["pose_source"] for s in sim} == {"sim"}
        assert len({tuple(s["pose"]) for s in sim}) > 1  # it moves
        assert all(s["at"] <= time.time() + 1 for s in sim)
        assert [s["at"] for s in sim] == sorted(s["at"] for s in sim)
        world = emulator.body.maze  # type: ignore[attr-defined]
        assert all(0 < s["pose"][0] < world.width and 0 < s["pose"][1] < world.height for s in sim)

        odo = client.get("/api/robots/r-odo/traces", params={"limit": 1000}).json()["samples"]
        assert {s["pose_source"] for s in odo} == {"odometry"}
        replayed = Odometry((1.0, 2.0, 0.0), World())
        for sample in odo:  # each sample's pose integrates the commands sent before it
            assert tuple(sample["pose"]) == replayed.pose
            replayed.advance(*sample["motors"])
        assert odo[0]["pose"] == [1.0, 2.0, 0.0] and odo[-1]["pose"][0] > 1.0

        reply = client.get("/api/colony/map").json()
        assert reply["maze"]["name"] == "paper" and len(reply["maze"]["rows"]) > 0
        assert reply["maze"]["rows"] == load_rows("paper")
        robots = {r["id"]: r for r in reply["robots"]}
        assert robots["r-odo"]["pose_source"] == "odometry" and robots["r-odo"]["online"]
        assert robots["r-sim"]["pose_source"] == "sim"
        assert len(robots["r-sim"]["path"]) > 10
        assert robots["r-sim"]["path"][-1] == robots["r-sim"]["pose"][:2]
        few = client.get("/api/colony/map", params={"samples": 5}).json()["robots"]
        assert all(len(r["path"]) <= 5 for r in few)
        refused = client.get("/api/colony/map", params={"samples": 0})
        assert refused.status_code == 422 and "samples" in refused.text


def load_rows(name: str) -> list[str]:
    from evorobotics.maze import load_maze

    return load_maze(name).text().splitlines()


def test_the_map_maze_is_a_server_setting_checked_at_start(tmp_path: Path) -> None:
    from pydantic import ValidationError

    from server.robots.map import maze_out

    lab = tmp_path / "lab.txt"
    lab.write_text("#####\n#...#\n#.#.#\n#####\n")
    shown = maze_out(Settings(db_url="sqlite://", maze=str(lab)).maze)
    assert (shown.name, shown.rows, shown.width) == (
        "lab",
        ["#####", "#...#", "#.#.#", "#####"],
        0.5,
    )
    with pytest.raises(ValidationError, match="unknown maze 'nowhere'"):
        Settings(db_url="sqlite://", maze="nowhere")


def test_the_agent_cli_refuses_a_malformed_start_pose(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from colony.cli import app as cli

    args = ["agent", "--robot-id", "r-cli", "--serial", "loop://", "--insecure-no-verify"]
    args += ["--state-dir", str(tmp_path), "--start-pose"]
    for bad, reason in [("1,2", "3 numbers"), ("1,2,nan", "finite"), ("a,b,c", "3 numbers")]:
        result = CliRunner().invoke(cli, [*args, bad])
        assert result.exit_code == 2 and reason in result.output, result.output


def _row(
    robot: str, boot: int, first: int, poses: np.ndarray | None, source: str = "odometry"
) -> TraceRow:
    n = 10
    return TraceRow(
        robot_id=robot,
        boot=boot,
        first=first,
        last=first + n - 1,
        count=n,
        controllers="[]",
        steps=np.arange(first, first + n, dtype="<i8").tobytes(),
        whiskers=np.zeros((n, 5), "|u1").tobytes(),
        motors=np.zeros((n, 2), "<f8").tobytes(),
        controller=np.full(n, -1, "<i4").tobytes(),
        fresh=np.zeros(n, "|b1").tobytes(),
        times=None if poses is None else np.arange(n, dtype="<f8").tobytes(),
        poses=None if poses is None else poses.astype("<f8").tobytes(),
        pose_source=None if poses is None else source,
    )


def test_the_map_places_stuck_events_at_their_steps_pose(engine: sa.Engine) -> None:
    """Newest `samples` poses per robot, across batches; a stuck event at the pose of its
    (boot, step) when that sample is among them, else not drawn; batches without poses and
    robots without any give no path."""
    from sqlalchemy.orm import sessionmaker

    from server.core.models import Robot
    from server.robots.map import colony_map

    def line(start: float) -> np.ndarray:
        xs = start + np.arange(10) * 0.01
        return np.stack([xs, np.full(10, 1.0), np.zeros(10)], axis=1)

    sessions = sessionmaker(engine)
    with sessions.begin() as db:
        db.add_all([Robot(id="r-map", status="online"), Robot(id="r-none", status="offline")])
        db.add_all([_row("r-map", 0, 0, None), _row("r-map", 1, 0, line(0.5))])
        db.add(_row("r-map", 1, 10, line(0.6)))
        db.add_all(
            [
                StuckEventRow(robot_id="r-map", reason="r", step=13, boot=1),  # retained
                StuckEventRow(robot_id="r-map", reason="r", step=2, boot=1),  # beyond `samples`
                StuckEventRow(robot_id="r-map", reason="r", step=3, boot=0),  # no pose
            ]
        )
    with sessions() as db:
        shown = colony_map(db, "paper", lambda robot: robot == "r-map", samples=15)
    robots = {r.id: r for r in shown.robots}
    assert robots["r-none"].pose is None and robots["r-none"].path == []
    mapped = robots["r-map"]
    assert mapped.online and mapped.pose_source == "odometry"
    assert len(mapped.path) == 15 and mapped.path[0] == pytest.approx((0.55, 1.0))
    assert mapped.pose is not None and mapped.pose == pytest.approx((0.69, 1.0, 0.0))
    assert mapped.path[-1] == mapped.pose[:2]
    assert [(m.step, round(m.x, 9), m.y) for m in mapped.stuck] == [(13, 0.63, 1.0)]


def test_the_map_draws_a_path_in_one_frame_only(engine: sa.Engine) -> None:
    """An agent with a tracker traces odometry (its own frame) until the tracker's first pose,
    then tracker poses (the maze's): the path is the newest source's alone, never a line
    from one frame to the other."""
    from sqlalchemy.orm import sessionmaker

    from server.core.models import Robot
    from server.robots.map import colony_map

    odometry = np.tile([0.0, 0.0, 0.0], (10, 1))  # where its --start-pose put it
    tracked = np.stack([np.linspace(1.0, 1.09, 10), np.full(10, 1.0), np.zeros(10)], axis=1)
    sessions = sessionmaker(engine)
    with sessions.begin() as db:
        db.add(Robot(id="r-frames", status="online"))
        db.add_all(
            [
                _row("r-frames", 1, 0, odometry),
                _row("r-frames", 1, 10, tracked, "tracker"),
                _row("r-frames", 1, 20, tracked + np.array([0.1, 0.0, 0.0]), "tracker"),
            ]
        )
    with sessions() as db:
        shown = colony_map(db, "paper", lambda robot: True, samples=600)
    mapped = next(r for r in shown.robots if r.id == "r-frames")
    assert mapped.pose_source == "tracker" and len(mapped.path) == 20
    assert min(x for x, _ in mapped.path) == pytest.approx(1.0)
