"""The robot agent over real ptys (BasicX emulator), without a server: the robot's own duties.

Server-side behaviour (pushes, traces, replacements) is in test_robots_server.py.
"""

from __future__ import annotations

import base64
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.document import ControllerDocument
from robot_agent.agent import Agent, validate_document
from robot_agent.driver import BasicXDriver
from robot_agent.emulator import BasicXEmulator
from robot_agent.sim_body import SimBody
from robot_agent.stuck import StuckConfig
from schemas.network import PRESETS, NetworkSpec
from tests.helpers import (
    AGENT_WAIT,
    constant_drive,
    eventually,
    free_port,
    offline_settings,
    random_controller,
    save,
)

SPEC = PRESETS["reactive"]


@pytest.fixture
def emulator() -> Iterator[BasicXEmulator]:
    with BasicXEmulator(SimBody.create("paper", seed=3)) as emu:
        yield emu


# ---------------------------------------------------------------------------- validation


def test_validate_accepts_a_document_and_checks_the_named_sha() -> None:
    doc = random_controller(1)
    assert validate_document(doc.to_json(), doc.sha256).sha256 == doc.sha256
    with pytest.raises(ValueError, match="hashes to"):
        validate_document(doc.to_json(), "0" * 64)


def test_validate_rejects_a_network_an_evbot_cannot_run() -> None:
    spec = NetworkSpec(inputs=4, hidden=(3,), delays=0, recurrence=0)
    doc = ControllerDocument(spec, np.zeros(spec.weight_count))
    with pytest.raises(ValueError, match="5 inputs and 2 outputs"):
        validate_document(doc.to_json())


@settings(max_examples=25, deadline=None)
@given(index=st.integers(0, SPEC.weight_count - 1), delta=st.sampled_from([1e-12, 1.0, -3.0]))
def test_validate_rejects_any_tampered_weight(index: int, delta: float) -> None:
    doc = random_controller(2)
    tampered = np.array(doc.weights)
    tampered[index] += delta
    forged = ControllerDocument(doc.spec, tampered).to_dict()
    forged["sha256"] = doc.sha256  # claims to be the original
    with pytest.raises(ValueError, match="sha256 mismatch"):
        validate_document(json.dumps(forged))


def test_validate_rejects_non_finite_weights() -> None:
    doc = random_controller(3).to_dict()
    raw = np.full(SPEC.weight_count, np.nan).astype("<f8").tobytes()

    doc["weights"]["data"] = base64.b64encode(raw).decode()
    with pytest.raises(ValueError, match="finite"):
        validate_document(json.dumps(doc))


# ---------------------------------------------------------------------------- offline agent


def test_agent_resumes_its_saved_controller_without_a_server(
    emulator: BasicXEmulator, tmp_path: Path
) -> None:
    doc = random_controller(4)
    save(tmp_path, doc)
    with BasicXDriver.open(emulator.port_path) as driver:
        agent = Agent(offline_settings("r1", tmp_path), driver)
        assert agent.boot == 0 and agent.controller == doc and agent.state == "running"
        with agent:
            assert agent.wait_for(lambda: agent.steps >= 20, AGENT_WAIT)
            assert not agent.connected.is_set()
    with BasicXDriver.open(emulator.port_path) as driver:
        again = Agent(offline_settings("r1", tmp_path), driver)
        assert again.boot == 1 and again.controller == doc


def test_corrupt_saved_controller_is_ignored(emulator: BasicXEmulator, tmp_path: Path) -> None:
    (tmp_path / "controller.json").write_text('{"format": "nope"}')
    with BasicXDriver.open(emulator.port_path) as driver:
        agent = Agent(offline_settings("r1", tmp_path), driver)
        assert agent.controller is None and agent.state == "idle"


def test_stuck_without_server_escapes_and_carries_on(
    emulator: BasicXEmulator, tmp_path: Path
) -> None:
    wall = constant_drive(0.9, 0.9)
    save(tmp_path, wall)
    cfg = offline_settings(
        "r1", tmp_path, stuck=StuckConfig(contact_steps=5), buffer_samples=10_000
    )
    with BasicXDriver.open(emulator.port_path) as driver, Agent(cfg, driver) as agent:
        assert agent.wait_for(lambda: agent.stuck_events >= 1, AGENT_WAIT)
        assert agent.wait_for(lambda: agent.state == "running", AGENT_WAIT)
        resumed = agent.steps
        assert agent.wait_for(lambda: agent.steps >= resumed + 2, AGENT_WAIT)
        with agent.changed:
            samples = list(agent._buffer)
    escape = [s for s in samples if s.sha256 is None]
    assert len(escape) == cfg.escape_back_steps + cfg.escape_turn_steps
    back = escape[: cfg.escape_back_steps]
    assert all(s.motors == (-cfg.escape_speed, -cfg.escape_speed) for s in back)
    after = samples[samples.index(escape[-1]) + 1]
    assert after.sha256 == wall.sha256 and after.fresh  # same controller, fresh state
    assert agent.controller == wall


def test_trace_buffer_is_bounded(emulator: BasicXEmulator, tmp_path: Path) -> None:
    save(tmp_path, random_controller(5))
    cfg = offline_settings("r1", tmp_path, buffer_samples=15)
    with BasicXDriver.open(emulator.port_path) as driver, Agent(cfg, driver) as agent:
        assert agent.wait_for(lambda: agent.dropped >= 10, AGENT_WAIT)
        assert agent.buffered() == 15
        with agent.changed:
            steps = [s.step for s in agent._buffer]
    assert steps == list(range(steps[0], steps[0] + 15))  # the newest, in order


def test_serial_garbage_is_survived(emulator: BasicXEmulator, tmp_path: Path) -> None:
    save(tmp_path, random_controller(6))
    with (
        BasicXDriver.open(emulator.port_path) as driver,
        Agent(offline_settings("r1", tmp_path), driver) as agent,
    ):
        assert agent.wait_for(lambda: agent.steps >= 5, AGENT_WAIT)
        emulator.inject(b"\x00\xff garbage $$ *ZZ\n$12 W*00\n" + os.urandom(300) + b"\n")
        emulator.corrupt_replies(4)
        before = agent.steps
        assert agent.wait_for(lambda: agent.steps >= before + 20 and agent.serial_ok, AGENT_WAIT)
    assert driver.stats.resends >= 1 or driver.stats.bad_lines >= 1


def test_killed_agent_motors_stop_by_the_firmware_watchdog(
    emulator: BasicXEmulator, tmp_path: Path
) -> None:
    """A real `colony agent` process on the pty, SIGKILLed while driving."""
    save(tmp_path, constant_drive(0.5, 0.4))
    port = free_port()
    proc = subprocess.Popen(
        [
            str(Path(sys.executable).with_name("colony")),
            "agent",
            "--robot-id",
            "killed",
            "--serial",
            emulator.port_path,
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--state-dir",
            str(tmp_path),
            "--log-level",
            "WARNING",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        driving = pytest.approx((0.5, 0.4), abs=1e-3)
        assert eventually(lambda: emulator.motors == driving, AGENT_WAIT)  # however slow to start
        assert emulator.wait_steps(emulator.steps + 5, AGENT_WAIT)
        assert emulator.motors == driving
        emulator.watchdog_tripped.clear()
        proc.send_signal(signal.SIGKILL)
        assert emulator.watchdog_tripped.wait(AGENT_WAIT)
        gap = emulator.watchdog_gap
        assert gap is not None and 0.5 <= gap < 0.6
        assert emulator.motors == (0.0, 0.0)
    finally:
        proc.kill()
        proc.communicate(timeout=AGENT_WAIT)
