"""Table rows (SQLAlchemy 2). Arrays are raw bytes with dtype and shape beside them.

Every schema change goes through an alembic revision in `server/migrations/versions`.
"""

from __future__ import annotations

from datetime import UTC, datetime

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


def aware(moment: datetime | None) -> datetime | None:
    """SQLite drops the zone of stored UTC times; put it back."""
    if moment is None or moment.tzinfo is not None:
        return moment
    return moment.replace(tzinfo=UTC)


class Base(DeclarativeBase):
    pass


class Study(Base):
    """Conditions x seeds runs of one base config (`schemas.study`); its runs point to it."""

    __tablename__ = "studies"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(64))
    spec: Mapped[str] = mapped_column(Text)
    """JSON: {"base": RunConfig, "conditions": {name: overrides} in order, "seeds": [...]}."""
    status: Mapped[str] = mapped_column(String(16))
    """Derived from its runs whenever one finishes (`crud.settle_study`)."""
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)


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
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    champion_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)
    """A completed run's validated champion in `controllers` (`RunManager.best`)."""
    name: Mapped[str | None] = mapped_column(String(128), nullable=True)
    tags: Mapped[str] = mapped_column(Text, default="[]", server_default="[]")
    """JSON list of strings."""
    study_id: Mapped[int | None] = mapped_column(
        ForeignKey("studies.id", ondelete="SET NULL"), nullable=True, index=True
    )
    condition: Mapped[str | None] = mapped_column(String(64), nullable=True)
    """Its condition in its study."""


class Generation(Base):
    """A committed generation: statistics and the GA state after `tell` (resume point)."""

    __tablename__ = "generations"

    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True)
    generation: Mapped[int] = mapped_column(Integer, primary_key=True)
    best: Mapped[float] = mapped_column(Float)
    mean: Mapped[float] = mapped_column(Float)
    worst: Mapped[float] = mapped_column(Float)
    nan_count: Mapped[int] = mapped_column(Integer, default=0)
    state: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    """At a checkpoint, the GA state after `tell` (`server.population.encode_state`), without
    `ranked` (this generation's genomes in rank order) since `population` holds them; None
    between checkpoints."""
    population: Mapped[bytes] = mapped_column(LargeBinary, deferred=True)
    """What the generation was told, in ask order (`server.runs.population`): fitness, descriptors
    for a strategy that resumes from them, and at a checkpoint its genomes and components.
    Deferred: listing generations reads only their statistics."""
    committed_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


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


class Robot(Base):
    """An EvBot of the colony and the controller it runs (filled by the robot registry)."""

    __tablename__ = "robots"

    id: Mapped[str] = mapped_column(String(128), primary_key=True)
    status: Mapped[str] = mapped_column(String(16))
    controller_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)
    first_seen: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    last_seen: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    replacement: Mapped[str | None] = mapped_column(String(16), nullable=True)
    """Its own replacement policy (`schemas.robots.ReplacementPolicy`); None: the colony's."""
    calibration: Mapped[str | None] = mapped_column(Text, nullable=True)
    """Its physics fitted from its traces (`schemas.robots.RobotCalibration` JSON); None: never."""
    calibrated_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    served: Mapped[str | None] = mapped_column(Text, nullable=True)
    """JSON list of the sha256s the server gave it (acknowledged pushes, replacements sent),
    oldest first, the newest `SERVED_KEPT`: only these count in field statistics."""
