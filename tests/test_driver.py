"""The agent's serial driver against the BasicX emulator over a real pty."""

import time
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robot_agent.driver import BasicXDriver, DriverConfig, open_port
from robot_agent.emulator import FIRMWARE_VERSION, BasicXEmulator
from robot_agent.errors import FirmwareError, LinkDeadError
from robot_agent.serial_protocol import encode
from tests.helpers import FixedBody


@pytest.fixture
def emulator() -> Iterator[BasicXEmulator]:
    with BasicXEmulator(FixedBody()) as emu:
        yield emu


@pytest.fixture
def driver(emulator: BasicXEmulator) -> Iterator[BasicXDriver]:
    with BasicXDriver.open(emulator.port_path) as drv:
        yield drv


def test_version_whiskers_motors_stop(emulator: BasicXEmulator, driver: BasicXDriver) -> None:
    assert driver.version() == FIRMWARE_VERSION
    assert driver.whiskers() == (True, False, True, False, False)
    driver.set_motors(0.5, -0.25)
    assert emulator.motors == (0.5, -0.25)
    driver.set_motors(3.0, -7.0)
    assert emulator.motors == (1.0, -1.0)
    driver.stop()
    assert emulator.motors == (0.0, 0.0)
    assert driver.stats.resends == 0


def test_garbage_on_the_line_is_survived(emulator: BasicXEmulator, driver: BasicXDriver) -> None:
    noise = np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes()
    emulator.inject(noise)
    assert driver.whiskers() == (True, False, True, False, False)
    emulator.inject(b"\x00\xff$$--partial frame without end")
    assert driver.version() == FIRMWARE_VERSION


@settings(
    max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.binary(min_size=1, max_size=500))
def test_any_noise_then_requests_succeed(
    emulator: BasicXEmulator, driver: BasicXDriver, noise: bytes
) -> None:
    emulator.inject(noise)
    driver.set_motors(0.1, 0.2)
    assert emulator.motors == (0.1, 0.2)
    assert driver.whiskers() == (True, False, True, False, False)


def test_corrupt_reply_is_retried(emulator: BasicXEmulator, driver: BasicXDriver) -> None:
    emulator.corrupt_replies(2)
    assert driver.version() == FIRMWARE_VERSION
    assert driver.stats.resends == 2
    assert driver.stats.bad_lines >= 2


def test_stale_reply_is_dropped(emulator: BasicXEmulator, driver: BasicXDriver) -> None:
    emulator.inject(encode(0xEE, "W 11111"))
    assert driver.whiskers() == (True, False, True, False, False)
    assert driver.stats.stale_replies == 1


def test_firmware_refusal_is_not_retried(driver: BasicXDriver) -> None:
    with pytest.raises(FirmwareError, match="ERR CMD"):
        driver.request("X")
    with pytest.raises(FirmwareError, match="ERR ARG"):
        driver.request("M 5000 0")
    assert driver.stats.resends == 0


def test_dead_link_is_reported_within_its_bound(
    emulator: BasicXEmulator, driver: BasicXDriver
) -> None:
    emulator.set_mute(True)
    start = time.monotonic()
    with pytest.raises(LinkDeadError):
        driver.whiskers()
    elapsed = time.monotonic() - start
    assert elapsed <= driver.config.dead_after + 0.25
    assert driver.stats.resends == driver.config.retries
    emulator.set_mute(False)
    assert driver.version() == FIRMWARE_VERSION  # the link comes back


def test_vanished_port_is_a_dead_link() -> None:
    emu = BasicXEmulator(FixedBody()).start()
    drv = BasicXDriver.open(emu.port_path)
    try:
        assert drv.version() == FIRMWARE_VERSION
        emu.stop()
        with pytest.raises(LinkDeadError):
            drv.version()
    finally:
        drv.close()
        emu.stop()


def test_open_port_takes_urls_and_rejects_bad_baud() -> None:
    port = open_port("loop://", 9600)
    try:
        assert port.baudrate == 9600
    finally:
        port.close()
    with pytest.raises(ValueError):
        open_port("loop://", 0)


def test_config_and_argument_checks(driver: BasicXDriver) -> None:
    for kwargs in ({"reply_timeout": 0.0}, {"retries": -1}, {"poll_interval": 1.0}):
        with pytest.raises(ValueError):
            DriverConfig(**kwargs)
    with pytest.raises(ValueError):
        driver.set_watchdog(0.0)
    with pytest.raises(ValueError):
        driver.set_motors(float("nan"), 0.0)
