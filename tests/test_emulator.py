"""The BasicX emulator: firmware replies, watchdog, simulated physics, thread and process use."""

import os
import select
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import serial

from evorobotics.maze import load_maze
from evorobotics.sim import DEFAULT_WORLD, whisker_bits
from robot_agent.driver import BasicXDriver
from robot_agent.emulator import FIRMWARE_VERSION, BasicXEmulator, FirmwareConfig
from robot_agent.emulator import main as emulator_main
from robot_agent.serial_protocol import UNKNOWN_SEQ, Frame, LineDecoder, encode
from robot_agent.sim_body import SimBody, draw_gap
from schemas.run import RunConfig
from schemas.world import World, world_from_json


@pytest.fixture
def body() -> SimBody:
    return SimBody.create("paper", seed=3)


@pytest.fixture
def emulator(body: SimBody) -> Iterator[BasicXEmulator]:
    with BasicXEmulator(body) as emu:
        yield emu


def _exchange(port: serial.Serial, raw: bytes) -> Frame:
    """Write raw bytes, return the first decoded reply (within 1 s)."""
    port.write(raw)
    decoder = LineDecoder()
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:
        for item in decoder.feed(port.read(max(1, port.in_waiting))):
            if isinstance(item, Frame):
                return item
    raise AssertionError("no reply")


def test_raw_replies(emulator: BasicXEmulator) -> None:
    with serial.serial_for_url(emulator.port_path, timeout=0.05) as port:
        assert _exchange(port, encode(1, "V")) == Frame(1, f"V {FIRMWARE_VERSION}")
        assert _exchange(port, encode(2, "Q")) == Frame(2, "ERR CMD")
        assert _exchange(port, encode(3, "M 1 2 3")) == Frame(3, "ERR ARG")
        assert _exchange(port, encode(4, "T 0")) == Frame(4, "ERR ARG")
        corrupted = encode(5, "S")[:-3] + b"00\n"
        assert _exchange(port, corrupted) == Frame(UNKNOWN_SEQ, "ERR CK")
        assert _exchange(port, b"\x00\x01 noise\n" + encode(6, "S")) == Frame(6, "OK")


def test_watchdog_stops_motors_within_half_a_second(emulator: BasicXEmulator) -> None:
    with BasicXDriver.open(emulator.port_path) as driver:
        driver.set_motors(0.6, 0.6)
        assert emulator.motors == (0.6, 0.6)
        assert emulator.watchdog_tripped.wait(timeout=0.5 + 0.2)
        assert emulator.motors == (0.0, 0.0)
        gap = emulator.watchdog_gap
        assert gap is not None and 0.5 <= gap <= 0.5 + 0.25


def test_watchdog_is_configurable_and_fed_by_requests(emulator: BasicXEmulator) -> None:
    with BasicXDriver.open(emulator.port_path) as driver:
        driver.set_watchdog(0.4)
        driver.set_motors(0.2, 0.2)
        for _ in range(8):  # 10 Hz requests for 0.8 s keep a 0.4 s watchdog quiet
            assert not emulator.watchdog_tripped.wait(timeout=0.1)
            driver.whiskers()
        assert emulator.motors == (0.2, 0.2)
        assert emulator.watchdog_tripped.wait(timeout=0.5)
        gap = emulator.watchdog_gap
        assert gap is not None and 0.4 <= gap <= 0.4 + 0.25


def test_motors_move_the_simulated_robot(emulator: BasicXEmulator, body: SimBody) -> None:
    start = body.pose.copy()
    with BasicXDriver.open(emulator.port_path) as driver:
        driver.set_motors(0.5, 0.5)
        steps = emulator.steps
        assert emulator.wait_steps(steps + 3, timeout=2.0)
        driver.stop()
        moved = float(np.hypot(*(body.pose[0, :2] - start[0, :2])))
        assert moved > 0 or body.blocked
        assert driver.whiskers() == body.whiskers()


def test_whiskers_follow_the_simulator() -> None:
    maze = load_maze("paper")
    body = SimBody.create("paper", seed=1, gap=False)
    expected = whisker_bits(maze, body.pose, World())[0]
    assert body.whiskers() == tuple(bool(b) for b in expected)
    # drive straight until something touches: the robot is blocked before it enters a wall
    for _ in range(400):
        body.step(1.0, 1.0)
        if body.blocked:
            break
    assert body.blocked and any(body.whiskers())


def test_reality_gap_draws_are_in_the_paper_ranges_and_deterministic() -> None:
    gaps = [draw_gap(7, i) for i in range(50)]
    ranges = np.array([g.whisker_range[0] for g in gaps])
    gains = np.array([g.motor_gain[0] for g in gaps])
    assert (
        (DEFAULT_WORLD.gap_whisker_range[0] <= ranges)
        & (ranges <= DEFAULT_WORLD.gap_whisker_range[1])
    ).all()
    assert (np.abs(gains - 1) <= DEFAULT_WORLD.gap_motor_gain).all()
    assert ranges.shape == (50, 5) and len(set(ranges.ravel().tolist())) == 250
    assert np.array_equal(draw_gap(7, 3).motor_gain, gaps[3].motor_gain)
    a, b = SimBody.create("paper", seed=7, index=3), SimBody.create("paper", seed=7, index=3)
    assert np.array_equal(a.pose, b.pose)


def test_stop_closes_every_fd() -> None:
    emu = BasicXEmulator(SimBody.create("arena", seed=0)).start()
    fds = (emu._master, emu._slave, emu._wake_r, emu._wake_w)
    emu.stop()
    emu.stop()  # idempotent
    for fd in fds:
        with pytest.raises(OSError):
            os.fstat(fd)
    with pytest.raises(ValueError):
        FirmwareConfig(watchdog=0.0)


@pytest.mark.slow
def test_emulator_as_a_separate_process() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "robot_agent.emulator", "--maze", "paper", "--seed", "2"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 30.0)
        assert ready, "emulator process printed no pty path"
        path = proc.stdout.readline().strip()
        with BasicXDriver.open(path) as driver:
            assert driver.version() == FIRMWARE_VERSION
            assert len(driver.whiskers()) == 5
        proc.terminate()
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        if proc.stdout is not None:
            proc.stdout.close()


def test_a_virtual_robot_takes_the_world_of_a_run_config_or_champion(tmp_path: Path) -> None:
    world = World(dt=0.05, max_speed=0.2, whisker_range=0.08, stuck_after=3)
    config = RunConfig(world=world)
    assert world_from_json(config.model_dump_json()) == world
    assert world_from_json(world.model_dump_json()) == world
    body = SimBody.create("paper", seed=3, index=1, world=world)
    assert body.params == world and body.dt == 0.05
    for bad, reason in (("[1]", "world object"), ("{", "invalid JSON"), ('{"dt": -1}', "dt")):
        with pytest.raises(ValueError, match=reason):
            world_from_json(bad)
    broken = tmp_path / "world.json"
    broken.write_text('{"world": {"whisker_angles": [0, 0]}}')
    with pytest.raises(SystemExit) as exc:
        emulator_main(["--world", str(broken)])
    assert exc.value.code == 2


def test_a_world_without_the_gap_is_the_bodys_hidden_physics_exactly() -> None:
    """`colony agent --emulate --world FILE --no-gap` (and the emulator's `--no-gap`): each
    whisker's range and each wheel's gain are the world's, as a lab sets a robot it wants."""
    world = World(whisker_range=(0.03, 0.045, 0.06, 0.075, 0.09), motor_gain=(0.9, 1.1))
    body = SimBody.create("paper", seed=3, index=1, gap=False, world=world)
    assert body.gap.whisker_range.tolist() == [list(world.whisker_ranges)]
    assert body.gap.motor_gain.tolist() == [[0.9, 1.1]]
    drawn = SimBody.create("paper", seed=3, index=1, world=world)
    assert drawn.gap.motor_gain.tolist() != [[0.9, 1.1]]  # the gap draws around the world's


def test_a_virtual_robot_under_the_step_gap_model_draws_its_whiskers_every_step() -> None:
    world = World(gap_model="step")
    a, b = (SimBody.create("paper", seed=5, index=2, world=world) for _ in range(2))
    assert np.array_equal(a.gap.motor_gain, draw_gap(5, 2).motor_gain)
    seen = []
    for _ in range(30):
        assert np.array_equal(a.whisker_range, b.whisker_range)  # a pure function of the seed
        expected = whisker_bits(a.maze, a.pose, world, a.whisker_range)[0]
        assert a.whiskers() == tuple(bool(bit) for bit in expected)
        seen.append(a.whisker_range[0])
        a.step(0.5, 0.6)
        b.step(0.5, 0.6)
    ranges = np.array(seen)
    lo, hi = world.gap_whisker_range
    assert ranges.shape == (30, 5) and ((ranges >= lo) & (ranges <= hi)).all()
    assert (ranges[1:] != ranges[:-1]).all() and (ranges[:, 1:] != ranges[:, :-1]).all()
    other = SimBody.create("paper", seed=5, index=3, world=world)
    assert not np.array_equal(other.whisker_range, ranges[:1])
    trial = SimBody.create("paper", seed=5, index=2)
    assert trial.whisker_range.shape == (1, 5)
    trial.step(0.5, 0.6)
    assert np.array_equal(trial.whisker_range, draw_gap(5, 2).whisker_range)
