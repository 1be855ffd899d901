"""The agent's side of the BasicX serial link: requests with retries, resync and dead-link report.

The driver takes any pyserial-like port object (`open_port` wraps `serial.serial_for_url`, so a
device path, a pty slave from the emulator or ``loop://`` all work). Every request is idempotent
(set motors, read whiskers, version, stop, watchdog), so a request whose reply is missing or
corrupt is simply sent again with a new sequence number; a late reply to any attempt of the
same request is accepted, a reply to an older request is dropped. After `retries` resends
without a valid reply the driver raises LinkDeadError, at most about
``(retries + 1) * reply_timeout`` after the request started; meanwhile the firmware watchdog
stops the motors on its own.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol

import serial

from robot_agent.errors import FirmwareError, LinkDeadError
from robot_agent.serial_protocol import (
    UNKNOWN_SEQ,
    Command,
    ErrorCode,
    Frame,
    FrameError,
    LineDecoder,
    encode,
    motor_units,
    parse_pose,
    parse_whisker_bits,
)

DEFAULT_BAUD = 115_200


class SerialPort(Protocol):
    """What the driver needs from a port: the subset of `serial.Serial` it calls."""

    timeout: float | None

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes, /) -> int | None: ...

    def close(self) -> None: ...


@dataclass(frozen=True, slots=True)
class DriverConfig:
    """Timing of the link; defaults fit a 10 Hz control loop (dt = 0.1 s) at 115200 baud."""

    reply_timeout: float = 0.05
    """Seconds to wait for a reply before resending (a round trip at 115200 baud is ~3 ms)."""
    retries: int = 3
    """Resends after the first attempt before the link is declared dead."""
    poll_interval: float = 0.01
    """Port read timeout: how often the reply wait rechecks its deadline."""

    def __post_init__(self) -> None:
        if not self.reply_timeout > 0:
            raise ValueError(f"reply_timeout must be > 0, got {self.reply_timeout}")
        if self.retries < 0:
            raise ValueError(f"retries must be >= 0, got {self.retries}")
        if not 0 < self.poll_interval <= self.reply_timeout:
            raise ValueError(
                f"poll_interval must be in (0, reply_timeout], got {self.poll_interval}"
            )

    @property
    def dead_after(self) -> float:
        """Upper bound, in seconds, on the wait before LinkDeadError (plus one poll)."""
        return (self.retries + 1) * self.reply_timeout + self.poll_interval


@dataclass(slots=True)
class LinkStats:
    """Counters of link health, for the agent's status and traces."""

    requests: int = 0
    resends: int = 0
    bad_lines: int = 0
    stale_replies: int = 0


def open_port(url: str, baud: int = DEFAULT_BAUD, *, poll_interval: float = 0.01) -> serial.Serial:
    """Open any pyserial port or URL (device path, pty slave, ``loop://``, ``rfc2217://``)."""
    if baud <= 0:
        raise ValueError(f"baud must be > 0, got {baud}")
    port: serial.Serial = serial.serial_for_url(url, baudrate=baud, timeout=poll_interval)
    return port


class BasicXDriver:
    """Typed requests to the BasicX firmware over one port; not thread-safe (one loop owns it)."""

    def __init__(self, port: SerialPort, config: DriverConfig | None = None) -> None:
        self.config = config or DriverConfig()
        self.stats = LinkStats()
        self._port = port
        self._port.timeout = self.config.poll_interval
        self._decoder = LineDecoder()
        self._seq = 0

    @classmethod
    def open(
        cls, url: str, baud: int = DEFAULT_BAUD, config: DriverConfig | None = None
    ) -> BasicXDriver:
        """Open `url` with pyserial and wrap it."""
        config = config or DriverConfig()
        return cls(open_port(url, baud, poll_interval=config.poll_interval), config)

    def version(self) -> str:
        """The firmware's version text."""
        return self._expect(self.request(Command.VERSION), Command.VERSION)

    def whiskers(self) -> tuple[bool, ...]:
        """The five whisker bits, left to right, sampled when the firmware got the request."""
        bits = self._expect(self.request(Command.WHISKERS), Command.WHISKERS)
        try:
            return parse_whisker_bits(bits)
        except ValueError as exc:
            raise FirmwareError(f"firmware sent bad whisker bits {bits!r}") from exc

    def pose(self) -> tuple[float, float, float]:
        """The true pose (x m, y m, heading rad) of an emulated robot; a real BasicX has no
        such request and answers ERR CMD (FirmwareError): the agent then uses odometry."""
        text = self._expect(self.request(Command.POSE), Command.POSE)
        try:
            return parse_pose(text)
        except ValueError as exc:
            raise FirmwareError(f"firmware sent a bad pose {text!r}") from exc

    def set_motors(self, left: float, right: float) -> None:
        """Both wheel commands in [-1, 1] (clamped; quantised to 1/1000 on the wire)."""
        self._ok(self.request(f"{Command.MOTORS} {motor_units(left)} {motor_units(right)}"))

    def stop(self) -> None:
        """Both motors to zero now."""
        self._ok(self.request(Command.STOP))

    def set_watchdog(self, seconds: float) -> None:
        """Firmware stops the motors when no request arrives for `seconds` (1 ms resolution)."""
        ms = round(seconds * 1000)
        if not 1 <= ms <= 60_000:
            raise ValueError(f"watchdog must be within 0.001..60 s, got {seconds}")
        self._ok(self.request(f"{Command.WATCHDOG} {ms}"))

    def request(self, body: str) -> str:
        """Send one request body and return the reply body; retries, then LinkDeadError."""
        body = str(body)
        self.stats.requests += 1
        sent: set[int] = set()
        for attempt in range(self.config.retries + 1):
            if attempt:
                self.stats.resends += 1
            seq = self._next_seq()
            sent.add(seq)
            try:
                self._port.write(encode(seq, body))
                reply = self._await_reply(sent)
            except (OSError, serial.SerialException) as exc:
                raise LinkDeadError(f"serial port failed during {body!r}: {exc}") from exc
            if reply is None:
                continue
            if reply.body.startswith("ERR "):
                raise FirmwareError(f"firmware refused {body!r}: {reply.body}")
            return reply.body
        raise LinkDeadError(
            f"no valid reply to {body!r} after {self.config.retries + 1} attempts "
            f"({self.config.reply_timeout * 1000:.0f} ms each)"
        )

    def close(self) -> None:
        """Close the port (the firmware watchdog then stops the motors)."""
        self._port.close()

    def __enter__(self) -> BasicXDriver:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _await_reply(self, sent: set[int]) -> Frame | None:
        """The first valid reply to one of `sent`; None when the attempt is over: resend.

        An attempt ends at its timeout, or at once on a reply line that arrived corrupt. An
        ERR CK (a request the firmware could not read) names no request, so it may answer
        noise on the line rather than ours: the attempt goes on waiting for our reply until
        its timeout, and a burst of them cannot use up the attempts.
        """
        deadline = time.monotonic() + self.config.reply_timeout
        while time.monotonic() < deadline:
            chunk = self._port.read(max(1, self._port.in_waiting))
            corrupt = False
            for item in self._decoder.feed(chunk):
                if isinstance(item, FrameError):
                    self.stats.bad_lines += 1
                    corrupt = corrupt or item.checksum_failed
                elif item.seq in sent:
                    return item
                elif item.seq == UNKNOWN_SEQ and item.body == f"ERR {ErrorCode.CHECKSUM}":
                    self.stats.stale_replies += 1
                else:
                    self.stats.stale_replies += 1
            if corrupt:
                return None
        return None

    @staticmethod
    def _expect(body: str, verb: Command) -> str:
        prefix = f"{verb} "
        if not body.startswith(prefix):
            raise FirmwareError(f"expected a {verb!s} reply, got {body!r}")
        return body[len(prefix) :]

    @staticmethod
    def _ok(body: str) -> None:
        if body != "OK":
            raise FirmwareError(f"expected OK, got {body!r}")


__all__ = [
    "DEFAULT_BAUD",
    "BasicXDriver",
    "DriverConfig",
    "LinkStats",
    "SerialPort",
    "open_port",
]
