"""Random bytes on the serial line, from either end, over a real pty.

Noise injected by the emulator (towards the agent): the driver resynchronises and the next
`whiskers()` / `set_motors()` succeed. Noise written by the agent's side (towards the firmware):
the emulator keeps answering. Noise is raw bytes mixed with protocol-shaped fragments (`$`,
sequence numbers, verbs, bad checksums, over-long lines) but never a whole valid frame: a valid
frame is a real command, not noise.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from robot_agent.agent import Agent
from robot_agent.driver import BasicXDriver
from robot_agent.emulator import FIRMWARE_VERSION, BasicXEmulator
from robot_agent.serial_protocol import MAX_LINE, Frame, LineDecoder, encode
from robot_agent.sim_body import SimBody
from tests.helpers import AGENT_WAIT, FixedBody, constant_drive, offline_settings, save

BITS = (True, False, True, False, False)
FUZZ = settings(
    max_examples=30,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

fragments = st.sampled_from(
    [b"$", b"*", b"\n", b"\r", b"--", b"$01 ", b"W", b"M 1000 -1000", b"T 1", b"*00\n", b"V"]
)
noise = st.lists(
    st.one_of(
        st.binary(min_size=1, max_size=64),
        fragments,
        st.builds(lambda seq: encode(seq, "W")[:-3] + b"ZZ\n", st.integers(0, 255)),
        st.just(b"x" * (MAX_LINE + 7)),
    ),
    min_size=1,
    max_size=12,
).map(b"".join)


def no_frame(data: bytes) -> bool:
    """True when no line of `data` decodes as a valid frame (that would be a command)."""
    return not any(isinstance(item, Frame) for item in LineDecoder().feed(data + b"\n"))


@pytest.fixture
def link() -> Iterator[tuple[BasicXEmulator, BasicXDriver, serial.Serial]]:
    """Emulator, driver and a second write-only handle on the agent's end of the pty."""
    body = FixedBody()
    with (
        BasicXEmulator(body) as emulator,
        BasicXDriver.open(emulator.port_path) as driver,
        serial.serial_for_url(emulator.port_path, timeout=0.05) as stray,
    ):
        yield emulator, driver, stray


@FUZZ
@given(data=noise)
def test_driver_resynchronises_after_noise_from_the_firmware_side(
    link: tuple[BasicXEmulator, BasicXDriver, serial.Serial], data: bytes
) -> None:
    emulator, driver, _ = link
    emulator.inject(data)
    assert driver.whiskers() == BITS
    driver.set_motors(0.3, -0.4)
    assert emulator.motors == (0.3, -0.4)


@FUZZ
@given(data=noise)
def test_emulator_survives_noise_from_the_agent_side(
    link: tuple[BasicXEmulator, BasicXDriver, serial.Serial], data: bytes
) -> None:
    assume(no_frame(data))
    emulator, driver, stray = link
    stray.write(data + b"\n")  # a line's end, so the noise cannot glue onto the next request
    stray.flush()
    driver.set_motors(-0.2, 0.7)
    assert emulator.motors == (-0.2, 0.7)
    assert driver.whiskers() == BITS
    assert driver.version() == FIRMWARE_VERSION


@settings(max_examples=3, deadline=None)
@given(towards_agent=noise, towards_firmware=noise)
def test_running_agent_keeps_stepping_through_noise_both_ways(
    towards_agent: bytes, towards_firmware: bytes
) -> None:
    """The whole agent (control thread, driver, watchdog) over noise in both directions."""
    assume(no_frame(towards_firmware))
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp)
        save(state, constant_drive(0.5, 0.5))
        with (
            BasicXEmulator(SimBody.create("paper", seed=4)) as emulator,
            BasicXDriver.open(emulator.port_path) as driver,
            serial.serial_for_url(emulator.port_path, timeout=0.05) as stray,
            Agent(offline_settings("noisy", state), driver) as agent,
        ):
            assert agent.wait_for(lambda: agent.steps >= 3, AGENT_WAIT)
            for _ in range(3):
                emulator.inject(towards_agent)
                stray.write(towards_firmware + b"\n")
                stray.flush()
            steps = agent.steps
            assert agent.wait_for(lambda: agent.steps >= steps + 10, AGENT_WAIT)
            assert agent.wait_for(lambda: agent.status().serial_ok, AGENT_WAIT)
            assert emulator.motors != (0.0, 0.0)  # driving, not stopped by the watchdog
