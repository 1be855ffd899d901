"""Table rows (SQLAlchemy 2). Arrays are raw bytes with dtype and shape beside them.

Every schema change goes through an alembic revision in `server/migrations/versions`.
"""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
from sqlalchemy import (
    BigInteger,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    LargeBinary,
    String,
    Text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column


def utcnow() -> datetime:
    """Operations timestamps only (never in the science)."""
    return datetime.now(UTC)


class Base(DeclarativeBase):
    pass


class Run(Base):
    """One evolutionary run: its config, lifecycle and running totals."""

    __tablename__ = "runs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    config: Mapped[str] = mapped_column(Text)
    """RunConfig as JSON: the run is a pure function of it."""
    seed: Mapped[int] = mapped_column(BigInteger)
    status: Mapped[str] = mapped_column(String(16), index=True)
    generation: Mapped[int] = mapped_column(Integer, default=0)
    """Committed generations; also the index of the generation being evaluated."""
    evaluations: Mapped[int] = mapped_column(BigInteger, default=0)
    """Controllers evaluated (each over `trials` trials), counted once per job result."""
    best_fitness: Mapped[float | None] = mapped_column(Float, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    served: Mapped[int] = mapped_column(BigInteger, default=0)
    """Unused since fair sharing moved to the in-memory job queue (server.jobs); always 0."""
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)


class Generation(Base):
    """A committed generation: statistics and the GA state after `tell` (resume point)."""

    __tablename__ = "generations"

    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True)
    generation: Mapped[int] = mapped_column(Integer, primary_key=True)
    best: Mapped[float] = mapped_column(Float)
    mean: Mapped[float] = mapped_column(Float)
    worst: Mapped[float] = mapped_column(Float)
    nan_count: Mapped[int] = mapped_column(Integer, default=0)
    state: Mapped[bytes] = mapped_column(LargeBinary)
    """GAState.to_arrays() as an uncompressed .npz (loaded with allow_pickle=False), without
    `ranked` (this generation's individuals in rank order) since it is read back from there."""
    committed_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Individual(Base):
    """One evaluated controller of a committed generation, by rank (0 = fittest)."""

    __tablename__ = "individuals"

    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True)
    generation: Mapped[int] = mapped_column(Integer, primary_key=True)
    rank: Mapped[int] = mapped_column(Integer, primary_key=True)
    index: Mapped[int] = mapped_column(Integer)
    """Position in the population as asked (the job slices cut this order)."""
    parent: Mapped[int | None] = mapped_column(Integer, nullable=True)
    """Rank in the previous generation of the individual this one descends from."""
    fitness: Mapped[float | None] = mapped_column(Float, nullable=True)
    """Eq 12 averaged over trials; NULL for a failed (NaN) evaluation, which ranks last."""
    components: Mapped[bytes] = mapped_column(LargeBinary)
    """(trials, 4) float64: Eq 12's curve length, net offset, max offset, stuck per trial."""
    genome: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    """Raw genome bytes; NULL for a copy (Eq 11's elites, fill and k-2 elite repeat genomes
    already stored: three quarters of a generation), whose bytes are those of its origin. Read
    it through `crud.GENOME`, which resolves the origin."""
    dtype: Mapped[str] = mapped_column(String(16))
    shape: Mapped[str] = mapped_column(String(64))
    origin_generation: Mapped[int | None] = mapped_column(Integer, nullable=True)
    """With `origin_rank`, the row of the same run that holds a copy's genome bytes (always
    one with bytes: one hop, never a chain); NULL when the row has its own bytes."""
    origin_rank: Mapped[int | None] = mapped_column(Integer, nullable=True)


class Controller(Base):
    """A controller document, addressed by its sha256."""

    __tablename__ = "controllers"

    sha256: Mapped[str] = mapped_column(String(64), primary_key=True)
    document: Mapped[str] = mapped_column(Text)
    run_id: Mapped[int | None] = mapped_column(
        ForeignKey("runs.id", ondelete="SET NULL"), nullable=True
    )
    generation: Mapped[int | None] = mapped_column(Integer, nullable=True)
    fitness: Mapped[float | None] = mapped_column(Float, nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Worker(Base):
    """A simulation worker seen by the server (filled by the zenoh dispatcher, issue 5)."""

    __tablename__ = "workers"

    id: Mapped[str] = mapped_column(String(128), primary_key=True)
    status: Mapped[str] = mapped_column(String(16))
    jobs_done: Mapped[int] = mapped_column(BigInteger, default=0)
    first_seen: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    last_seen: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Robot(Base):
    """An EvBot of the colony and the controller it runs (filled by the robot registry)."""

    __tablename__ = "robots"

    id: Mapped[str] = mapped_column(String(128), primary_key=True)
    status: Mapped[str] = mapped_column(String(16))
    controller_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)
    first_seen: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    last_seen: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


def pack(array: np.ndarray) -> tuple[bytes, str, str]:
    """Raw little-endian C-order bytes, dtype name and shape ("100,222") of an array."""
    arr = np.ascontiguousarray(array)
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    return arr.tobytes(), arr.dtype.str, ",".join(str(n) for n in arr.shape)


def unpack(data: bytes, dtype: str, shape: str) -> np.ndarray:
    """Inverse of `pack` (a read-only view over `data`)."""
    dims = tuple(int(n) for n in shape.split(",")) if shape else ()
    return np.frombuffer(data, dtype=np.dtype(dtype)).reshape(dims)
