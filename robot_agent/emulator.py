"""A virtual BasicX: the firmware's side of docs/serial-protocol.md on a pseudo-terminal.

The emulator owns both ends of an `os.openpty` pair; the agent opens `port_path` (the slave)
with pyserial exactly as it opens /dev/ttyS0 on a real EvBot. A thread plays the firmware:
it answers requests, runs the watchdog (motors to zero when no valid request arrives for
`watchdog` seconds, default 0.5 s) and advances a `Body` by one physics step every `body.dt`
seconds of real time with the wheel commands in force. `robot_agent.sim_body.SimBody` is the
simulator's EvBot with the reality gap on; any object with `dt`, `step` and `whiskers` works.

Real time is deliberate here: the watchdog and the control rate are properties of the
hardware being emulated, so this module reads the monotonic clock; the science it drives
(`evorobotics`) never does. Run it as a separate process with
``python -m robot_agent.emulator --maze paper --seed 0`` (prints the pty path on stdout).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import select
import signal
import sys
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path
from types import FrameType, TracebackType
from typing import Protocol, runtime_checkable

from robot_agent.serial_protocol import (
    MOTOR_FULL_SCALE,
    UNKNOWN_SEQ,
    Command,
    ErrorCode,
    Frame,
    FrameError,
    LineDecoder,
    encode,
    pose_text,
    whisker_bits,
)

FIRMWARE_VERSION = "EvBot-BasicX 1.0 (emulated)"


class Body(Protocol):
    """The physics behind the firmware: one EvBot that moves and senses."""

    @property
    def dt(self) -> float:
        """Seconds of one physics step."""
        ...

    def step(self, left: float, right: float) -> None:
        """Advance one step with wheel commands in [-1, 1]."""
        ...

    def whiskers(self) -> tuple[bool, ...]:
        """The five whisker bits at the current pose, left to right."""
        ...


@runtime_checkable
class PosedBody(Body, Protocol):
    """A body that knows where it is: the emulator then answers the `P` (pose) request."""

    def position(self) -> tuple[float, float, float]:
        """x, y (metres) and heading (radians) now."""
        ...


@dataclass(frozen=True, slots=True)
class FirmwareConfig:
    """Behaviour of the emulated firmware."""

    watchdog: float = 0.5
    """Seconds without a valid request after which the motors stop (command T changes it)."""
    version: str = FIRMWARE_VERSION
    pose_request: bool = True
    """Answer `P` with a posed body's pose; False answers ERR as a real BasicX does (its pose
    then reaches the server only through a tracker, `robot_agent.tracker`)."""

    def __post_init__(self) -> None:
        if not 0.001 <= self.watchdog <= 60:
            raise ValueError(f"watchdog must be within 0.001..60 s, got {self.watchdog}")


class BasicXEmulator:
    """The firmware on a pty, run by one thread between `start()` and `stop()` (or `with`)."""

    def __init__(self, body: Body, config: FirmwareConfig | None = None) -> None:
        self.config = config or FirmwareConfig()
        self.body = body
        self.watchdog_tripped = threading.Event()
        """Set each time the watchdog stops running motors; tests clear and wait on it."""
        self._watchdog = self.config.watchdog
        self._lock = threading.Lock()
        self._stepped = threading.Condition(self._lock)
        self._motors = (0, 0)
        self._last_request: float | None = None
        self._stopped_at: float | None = None
        self._steps = 0
        self._pose: tuple[float, tuple[float, float, float]] | None = None
        """Wall time of the last physics step, and a posed body's pose after it."""
        self._mute = False
        self._corrupt = 0
        self._pending_noise = bytearray()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port_path = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()
        self._decoder = LineDecoder()

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> BasicXEmulator:
        """Start the firmware thread; returns self."""
        if self._thread is not None:
            raise RuntimeError("emulator already started")
        self._thread = threading.Thread(target=self._run, name="basicx-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and close every fd it owns (idempotent)."""
        self._halt.set()
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                raise RuntimeError("emulator thread did not stop")
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = self._wake_r = self._wake_w = -1

    def __enter__(self) -> BasicXEmulator:
        return self.start() if self._thread is None else self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    # ------------------------------------------------------------------ observation

    @property
    def motors(self) -> tuple[float, float]:
        """Wheel commands in force, in [-1, 1]."""
        with self._lock:
            left, right = self._motors
        return left / MOTOR_FULL_SCALE, right / MOTOR_FULL_SCALE

    @property
    def watchdog_gap(self) -> float | None:
        """Seconds from the last valid request to the last watchdog stop (None if never)."""
        with self._lock:
            if self._stopped_at is None or self._last_request is None:
                return None
            return self._stopped_at - self._last_request

    @property
    def steps(self) -> int:
        """Physics steps taken since start."""
        with self._lock:
            return self._steps

    def wait_steps(self, count: int, timeout: float) -> bool:
        """Block until `count` physics steps have been taken since start; False on timeout."""
        with self._stepped:
            return self._stepped.wait_for(lambda: self._steps >= count, timeout)

    def wait_pose(
        self, count: int, timeout: float
    ) -> tuple[int, float, tuple[float, float, float]] | None:
        """Once `count` physics steps were taken: (steps, wall time of the last, the posed
        body's pose after it), as an overhead camera sees it; None on timeout or no pose."""
        with self._stepped:
            if not self._stepped.wait_for(lambda: self._steps >= count, timeout):
                return None
            return None if self._pose is None else (self._steps, *self._pose)

    # ------------------------------------------------------------------ fault injection

    def set_mute(self, mute: bool) -> None:
        """Ignore every request (a dead link): the watchdog still runs."""
        with self._lock:
            self._mute = mute

    def corrupt_replies(self, count: int) -> None:
        """Send the next `count` replies with a wrong checksum."""
        if count < 0:
            raise ValueError(f"count must be >= 0, got {count}")
        with self._lock:
            self._corrupt = count

    def inject(self, noise: bytes) -> None:
        """Put raw bytes on the line towards the agent (before the next reply)."""
        with self._lock:
            self._pending_noise += noise
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    # ------------------------------------------------------------------ the firmware

    def _run(self) -> None:
        next_step = time.monotonic() + self.body.dt
        while not self._halt.is_set():
            now = time.monotonic()
            deadline = next_step
            with self._lock:
                if self._motors != (0, 0) and self._last_request is not None:
                    deadline = min(deadline, self._last_request + self._watchdog)
            ready, _, _ = select.select(
                [self._master, self._wake_r], [], [], max(0.0, deadline - now)
            )
            if self._wake_r in ready:
                os.read(self._wake_r, 64)
            self._flush_noise()
            if self._master in ready:
                self._receive()
            now = time.monotonic()
            self._check_watchdog(now)
            while now >= next_step:
                with self._lock:
                    left, right = self._motors
                self.body.step(left / MOTOR_FULL_SCALE, right / MOTOR_FULL_SCALE)
                pose = self.body.position() if isinstance(self.body, PosedBody) else None
                with self._lock:
                    self._steps += 1
                    if pose is not None:
                        self._pose = (time.time(), pose)
                    self._stepped.notify_all()
                next_step += self.body.dt

    def _check_watchdog(self, now: float) -> None:
        with self._lock:
            if (
                self._motors != (0, 0)
                and self._last_request is not None
                and now - self._last_request >= self._watchdog
            ):
                self._motors = (0, 0)
                self._stopped_at = now
                self.watchdog_tripped.set()

    def _receive(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except OSError as exc:  # EIO: no slave open; EAGAIN: spurious wake-up
            if exc.errno in (errno.EIO, errno.EAGAIN):
                return
            raise
        for item in self._decoder.feed(data):
            with self._lock:
                mute = self._mute
            if mute:
                continue
            if isinstance(item, FrameError):
                # only an intact-looking frame gets an answer; bare noise is ignored
                if b"$" in item.line:
                    self._send(UNKNOWN_SEQ, f"ERR {ErrorCode.CHECKSUM}")
                continue
            self._send(item.seq, self._handle(item))

    def _handle(self, frame: Frame) -> str:
        """Reply body to one valid request; any valid request feeds the watchdog."""
        now = time.monotonic()
        with self._lock:
            self._last_request = now
        words = frame.body.split()
        if not words:
            return f"ERR {ErrorCode.COMMAND}"
        verb, args = words[0], words[1:]
        if verb == Command.VERSION and not args:
            return f"{Command.VERSION} {self.config.version}"
        if verb == Command.WHISKERS and not args:
            return f"{Command.WHISKERS} {whisker_bits(self.body.whiskers())}"
        if verb == Command.POSE:
            body = self.body
            if not isinstance(body, PosedBody) or not self.config.pose_request:
                return f"ERR {ErrorCode.COMMAND}"  # as a real BasicX: it has no such request
            if args:
                return f"ERR {ErrorCode.ARGUMENT}"
            return f"{Command.POSE} {pose_text(*body.position())}"
        if verb == Command.STOP and not args:
            with self._lock:
                self._motors = (0, 0)
            return "OK"
        if verb == Command.MOTORS:
            values = _ints(args, 2, -MOTOR_FULL_SCALE, MOTOR_FULL_SCALE)
            if values is None:
                return f"ERR {ErrorCode.ARGUMENT}"
            with self._lock:
                self._motors = (values[0], values[1])
            return "OK"
        if verb == Command.WATCHDOG:
            values = _ints(args, 1, 1, 60_000)
            if values is None:
                return f"ERR {ErrorCode.ARGUMENT}"
            with self._lock:
                self._watchdog = values[0] / 1000
            return "OK"
        if verb in tuple(Command):
            return f"ERR {ErrorCode.ARGUMENT}"
        return f"ERR {ErrorCode.COMMAND}"

    def _send(self, seq: int, body: str) -> None:
        line = encode(seq, body)
        with self._lock:
            corrupt = self._corrupt > 0
            if corrupt:
                self._corrupt -= 1
        if corrupt:
            # flip the last checksum digit: the frame still parses, its checksum fails
            line = line[:-2] + (b"0" if line[-2:-1] != b"0" else b"1") + b"\n"
        self._write(line)

    def _flush_noise(self) -> None:
        with self._lock:
            noise = bytes(self._pending_noise)
            self._pending_noise.clear()
        if noise:
            self._write(noise)

    def _write(self, data: bytes) -> None:
        """Write towards the agent; drop what the pty cannot take, as a UART overruns."""
        with contextlib.suppress(BlockingIOError):
            os.write(self._master, data)


def _ints(args: list[str], count: int, lo: int, hi: int) -> list[int] | None:
    if len(args) != count:
        return None
    try:
        values = [int(a) for a in args]
    except ValueError:
        return None
    return values if all(lo <= v <= hi for v in values) else None


def main(argv: list[str] | None = None) -> int:
    """Run one virtual EvBot as a process: print the pty path, serve until SIGTERM/SIGINT."""
    from evorobotics.sim import DEFAULT_WORLD
    from robot_agent.sim_body import SimBody
    from schemas.world import world_from_json

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--maze", default="paper", help="maze name, gen:SIZE:SEED or path")
    parser.add_argument("--seed", type=int, default=0, help="seed of the start pose and gap")
    parser.add_argument("--index", type=int, default=0, help="robot index within the seed")
    parser.add_argument("--watchdog-ms", type=int, default=500)
    parser.add_argument("--no-gap", action="store_true", help="nominal whiskers and motors")
    parser.add_argument(
        "--world", help="JSON file: a world, or a config.json / best.json with one (default World)"
    )
    args = parser.parse_args(argv)
    world = DEFAULT_WORLD
    if args.world is not None:
        try:
            world = world_from_json(Path(args.world).read_bytes())
        except (OSError, ValueError) as exc:
            parser.error(f"--world {args.world}: {exc}")
    body = SimBody.create(
        args.maze, seed=args.seed, index=args.index, gap=not args.no_gap, world=world
    )
    done = threading.Event()

    def _on_signal(signum: int, frame: FrameType | None) -> None:
        done.set()

    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    with BasicXEmulator(body, FirmwareConfig(watchdog=args.watchdog_ms / 1000)) as emulator:
        sys.stdout.write(f"{emulator.port_path}\n")
        sys.stdout.flush()
        while not done.wait(1.0):
            pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
