"""Tables of the robot side: trace batches, each robot's last report, stuck events, field stats.

Defined on `server.models.Base` so one metadata (and alembic revision 0002) covers them. Arrays
are raw little-endian bytes as everywhere in the store; a trace batch keeps its samples together
because they arrive, are replayed and expire together. `served`, `serve` and `field_row` keep
what the server gave each robot and the field statistics that only those controllers earn.
"""

from __future__ import annotations

import json
from datetime import datetime

from sqlalchemy import BigInteger, Boolean, DateTime, Index, Integer, LargeBinary, String, Text
from sqlalchemy.orm import Mapped, Session, mapped_column

from server.core.integrity import DamagedRowError, checksum
from server.core.models import Base, Robot, utcnow

SERVED_KEPT = 64
"""Controllers a robot's `served` list remembers: far more than it runs between reports."""


class TraceRow(Base):
    """Consecutive samples of one robot within one agent start (`boot`)."""

    __tablename__ = "robot_traces"

    robot_id: Mapped[str] = mapped_column(String(128), primary_key=True)
    boot: Mapped[int] = mapped_column(Integer, primary_key=True)
    first: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    last: Mapped[int] = mapped_column(BigInteger)
    count: Mapped[int] = mapped_column(Integer)
    controllers: Mapped[str] = mapped_column(Text)
    """JSON list of sha256; `controller` indexes it (-1: escape or stopped)."""
    steps: Mapped[bytes] = mapped_column(LargeBinary)
    """(count,) <i8."""
    whiskers: Mapped[bytes] = mapped_column(LargeBinary)
    """(count, 5) |u1."""
    motors: Mapped[bytes] = mapped_column(LargeBinary)
    """(count, 2) <f8, exactly as the controller computed them."""
    controller: Mapped[bytes] = mapped_column(LargeBinary)
    """(count,) <i4."""
    fresh: Mapped[bytes] = mapped_column(LargeBinary)
    """(count,) |b1: the controller started from fresh state at this sample."""
    times: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    """(count,) <f8 Unix seconds of each sample (None: stored before traces carried poses)."""
    poses: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    """(count, 3) <f8 x, y (m), heading (rad) of each sample, from `pose_source`."""
    pose_source: Mapped[str | None] = mapped_column(String(16), nullable=True)
    """sim (an emulated robot's true pose) or odometry (integrated from its motor commands)."""
    received_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    checksum: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    """CRC-32 of its arrays (`trace_checksum`), verified on every read; None: stored before."""


TRACE_ARRAYS = ("steps", "whiskers", "motors", "controller", "fresh", "times", "poses")
"""The blob columns a trace batch's checksum covers, in order."""


def trace_checksum(row: TraceRow) -> int:
    return checksum(getattr(row, name) for name in TRACE_ARRAYS)


def check_trace(row: TraceRow) -> None:
    """DamagedRowError naming the batch if its arrays changed since they were stored."""
    if row.checksum is not None and trace_checksum(row) != row.checksum:
        raise DamagedRowError(
            f"robot {row.robot_id} boot {row.boot} trace batch from step {row.first}: stored "
            "bytes are damaged (checksum mismatch)"
        )


class RobotStateRow(Base):
    """The last report of a robot (from its newest trace batch) and who pushed what."""

    __tablename__ = "robot_state"

    robot_id: Mapped[str] = mapped_column(String(128), primary_key=True)
    state: Mapped[str] = mapped_column(String(16))
    steps: Mapped[int] = mapped_column(BigInteger, default=0)
    boot: Mapped[int] = mapped_column(Integer, default=0)
    whiskers: Mapped[str] = mapped_column(String(8), default="00000")
    controller_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)
    serial_ok: Mapped[bool] = mapped_column(Boolean, default=True)
    status: Mapped[str] = mapped_column(Text, default="{}")
    """The agent's RobotStatus as JSON."""
    stuck_events: Mapped[int] = mapped_column(Integer, default=0)
    """Stuck requests the server received from this robot."""
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class StuckEventRow(Base):
    """One stuck robot's request for a controller, and what the server sent back."""

    __tablename__ = "robot_stuck_events"
    __table_args__ = (Index("ix_stuck_robot", "robot_id", "id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    robot_id: Mapped[str] = mapped_column(String(128))
    controller_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True, index=True)
    reason: Mapped[str] = mapped_column(String(64))
    step: Mapped[int] = mapped_column(BigInteger)
    replacement_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)
    at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    policy: Mapped[str | None] = mapped_column(String(16), nullable=True)
    """The replacement policy in force for the robot (None: recorded before policies)."""
    answer: Mapped[str | None] = mapped_column(Text, nullable=True)
    """The reply's reason: the rank sent, or why nothing was."""
    boot: Mapped[int | None] = mapped_column(Integer, nullable=True)
    """The robot's boot as its last trace batch said: `step` counts from that agent start."""
    steps_run: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    """Steps from this event to the robot's next, if it then ran what this event left it with
    (the replacement, or its own controller without one) in the same boot; None until then."""


class FieldStatsRow(Base):
    """Field performance of one controller over every robot: steps run and stuck events."""

    __tablename__ = "controller_field_stats"

    sha256: Mapped[str] = mapped_column(String(64), primary_key=True)
    steps: Mapped[int] = mapped_column(BigInteger, default=0)
    """Control steps driven by this controller (escape steps excluded)."""
    stuck_events: Mapped[int] = mapped_column(Integer, default=0)


def served(robot: Robot | None) -> list[str]:
    """The controllers the server gave `robot` (oldest first): only their steps and stuck
    events count in field statistics, whatever a robot names."""
    return [] if robot is None or not robot.served else list(json.loads(robot.served))


def serve(robot: Robot, sha256: str) -> None:
    """Note that the server gave `robot` the controller `sha256`."""
    kept = [s for s in served(robot) if s != sha256] + [sha256]
    robot.served = json.dumps(kept[-SERVED_KEPT:])


def field_row(db: Session, sha256: str) -> FieldStatsRow:
    row = db.get(FieldStatsRow, sha256)
    if row is None:
        row = FieldStatsRow(sha256=sha256, steps=0, stuck_events=0)
        db.add(row)
    return row
