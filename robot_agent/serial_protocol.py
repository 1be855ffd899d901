"""Framing of the RS232 link between the agent and the BasicX firmware (docs/serial-protocol.md).

One frame per line: ``$SS BODY*CC\\n``. ``SS`` is a two-digit hex sequence number that the
firmware echoes in its reply (``--`` when it could not read the request's), ``BODY`` printable
ASCII, ``CC`` the XOR of every byte between ``$`` and ``*`` in two upper-case hex digits. A frame
starts at the last ``$`` of a line, so whatever noise precedes it on the line is skipped: that
is how both ends resynchronise after garbage. Pure functions and one incremental decoder, no I/O,
shared by the driver and the emulator so both ends agree byte for byte.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from enum import StrEnum

from robot_agent.errors import SerialLinkError

MAX_LINE = 96
"""Longest line either end buffers; a longer run of bytes without newline is noise."""

UNKNOWN_SEQ = -1
"""Sequence number of a reply to a request whose own sequence number could not be read."""

WHISKERS = 5
"""Binary whiskers on an EvBot, reported left to right (paper section 3)."""

MOTOR_FULL_SCALE = 1000
"""Wheel commands cross the wire as integers in [-1000, 1000]: per mille of full speed."""

_BODY = re.compile(r"[\x20-\x7e]*")
_FRAME = re.compile(rb"\$([0-9A-F]{2}|--) ([\x20-\x29\x2b-\x7e]*)\*([0-9A-F]{2})\r?")


class Command(StrEnum):
    """Request verbs of the agent (first word of a request body)."""

    MOTORS = "M"  # M <left> <right>   set both wheels, per mille; reply OK
    WHISKERS = "W"  # W                  read the whiskers; reply W <bits>
    VERSION = "V"  # V                  firmware version; reply V <text>
    STOP = "S"  # S                  both motors to zero at once; reply OK
    WATCHDOG = "T"  # T <ms>             set the watchdog timeout; reply OK
    POSE = "P"  # P                  the emulator's true pose; reply P <x> <y> <theta>


class ErrorCode(StrEnum):
    """Why the firmware refused a request (reply body ``ERR <code>``)."""

    CHECKSUM = "CK"  # the request line failed its checksum or framing: resend it
    COMMAND = "CMD"  # unknown verb
    ARGUMENT = "ARG"  # wrong number or range of arguments


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded line: sequence number (or UNKNOWN_SEQ) and body text."""

    seq: int
    body: str


def checksum(data: bytes) -> int:
    """XOR of the bytes: cheap enough for an 8-bit micro-controller, catches any 1-byte error."""
    value = 0
    for byte in data:
        value ^= byte
    return value


def encode(seq: int, body: str) -> bytes:
    """The wire bytes of one frame, newline included."""
    if not (seq == UNKNOWN_SEQ or 0 <= seq <= 0xFF):
        raise ValueError(f"seq must be 0..255 or UNKNOWN_SEQ, got {seq}")
    if "*" in body or "$" in body or not _BODY.fullmatch(body):
        raise ValueError(f"body must be printable ASCII without '$' or '*', got {body!r}")
    inner = ("--" if seq == UNKNOWN_SEQ else f"{seq:02X}") + " " + body
    raw = inner.encode("ascii")
    line = b"$" + raw + b"*" + f"{checksum(raw):02X}".encode("ascii") + b"\n"
    if len(line) > MAX_LINE:
        raise ValueError(f"frame of {len(line)} bytes exceeds MAX_LINE={MAX_LINE}")
    return line


class FrameError(SerialLinkError):
    """A line that is not a valid frame; `checksum_failed` if only its checksum is wrong."""

    def __init__(self, line: bytes, *, checksum_failed: bool) -> None:
        super().__init__(f"bad frame {line!r}")
        self.line = line
        self.checksum_failed = checksum_failed


def decode_line(line: bytes) -> Frame:
    """Decode one line (without its newline), starting at its last ``$``; raise FrameError."""
    start = line.rfind(b"$")
    candidate = line[start:] if start >= 0 else line
    match = _FRAME.fullmatch(candidate)
    if match is None:
        raise FrameError(line, checksum_failed=False)
    seq_text, body, check = match.groups()
    inner = seq_text + b" " + body
    if checksum(inner) != int(check, 16):
        raise FrameError(line, checksum_failed=True)
    seq = UNKNOWN_SEQ if seq_text == b"--" else int(seq_text, 16)
    return Frame(seq, body.decode("ascii"))


class LineDecoder:
    """Incremental decoder: feed it bytes as they arrive, get frames and bad lines back.

    Only the last MAX_LINE bytes of a line (from its last ``$`` if any) are kept, so noise
    without newlines cannot grow the buffer and a frame that follows noise still decodes.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[Frame | FrameError]:
        """Every complete line in `data` (plus what was buffered), decoded in order."""
        out: list[Frame | FrameError] = []
        for byte in data:
            if byte == 0x0A:
                line = bytes(self._buffer)
                self._buffer.clear()
                if line.strip(b"\r"):
                    try:
                        out.append(decode_line(line))
                    except FrameError as bad:
                        out.append(bad)
                continue
            if len(self._buffer) >= MAX_LINE:
                start = self._buffer.rfind(b"$")
                if start > 0:
                    del self._buffer[:start]
                else:
                    self._buffer.clear()
            self._buffer.append(byte)
        return out

    def reset(self) -> None:
        """Forget any partial line (after the port was flushed)."""
        self._buffer.clear()


def motor_units(value: float) -> int:
    """A wheel command in [-1, 1] as the wire's per-mille integer, clamped."""
    if value != value:  # NaN
        raise ValueError("motor command is NaN")
    clamped = max(-1.0, min(1.0, value))
    return round(clamped * MOTOR_FULL_SCALE)


def whisker_bits(whiskers: tuple[bool, ...]) -> str:
    """Whiskers as the wire's ``0``/``1`` string, left to right."""
    if len(whiskers) != WHISKERS:
        raise ValueError(f"need {WHISKERS} whiskers, got {len(whiskers)}")
    return "".join("1" if w else "0" for w in whiskers)


def parse_whisker_bits(text: str) -> tuple[bool, ...]:
    """Inverse of `whisker_bits`; ValueError on anything else."""
    if len(text) != WHISKERS or set(text) - {"0", "1"}:
        raise ValueError(f"whisker bits must be {WHISKERS} of 0/1, got {text!r}")
    return tuple(c == "1" for c in text)


def pose_text(x: float, y: float, theta: float) -> str:
    """A pose as the `P` reply's three numbers: shortest round-trip float text, so the agent
    reads the emulator's float64 pose bit for bit."""
    return " ".join(repr(float(v)) for v in (x, y, theta))


def parse_pose(text: str) -> tuple[float, float, float]:
    """Inverse of `pose_text`: three finite numbers (metres, metres, radians); ValueError else."""
    words = text.split()
    if len(words) != 3:
        raise ValueError(f"a pose is 3 numbers, got {text!r}")
    x, y, theta = (float(w) for w in words)
    if not all(math.isfinite(v) for v in (x, y, theta)):
        raise ValueError(f"a pose must be finite, got {text!r}")
    return x, y, theta
