"""Engine factory and schema migration: the database a lab keeps across upgrades."""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

log = logging.getLogger(__name__)

MIGRATIONS = Path(__file__).resolve().parent / "migrations"

BUSY_TIMEOUT_MS = 10_000
"""SQLite waits this long for a writer lock instead of failing at once."""


WAL_LIMIT_BYTES = 64 << 20
"""After a checkpoint SQLite truncates a larger write-ahead log back to this size."""


def make_engine(url: str, *, background_checkpoint: bool = False) -> Engine:
    """An engine for `url`; SQLite files get WAL, a busy timeout and foreign keys.

    `background_checkpoint`: writes never copy the write-ahead log into the database file
    themselves (SQLite's automatic checkpoint, every ~1000 pages, made the write of a generation
    more than twice as slow); the caller runs a `Checkpointer` instead.
    """
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        return create_engine(url, pool_pre_ping=True)
    database = parsed.database or ""
    if database in ("", ":memory:"):
        raise ValueError("use an SQLite file URL (sqlite:///path.db): the server needs WAL")
    Path(database).expanduser().parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(url, connect_args={"check_same_thread": False})

    @event.listens_for(engine, "connect")
    def _pragmas(dbapi_connection: Any, _record: Any) -> None:
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute(f"PRAGMA busy_timeout={BUSY_TIMEOUT_MS}")
        cursor.execute("PRAGMA synchronous=NORMAL")  # WAL keeps whole transactions on crash
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute(f"PRAGMA journal_size_limit={WAL_LIMIT_BYTES}")
        if background_checkpoint:
            cursor.execute("PRAGMA wal_autocheckpoint=0")
        cursor.close()

    return engine


def is_sqlite(engine: Engine) -> bool:
    return engine.dialect.name == "sqlite"


class Checkpointer:
    """Copies SQLite's write-ahead log into the database file every `interval_s`, off the
    writers' path: a PASSIVE checkpoint never blocks a writer or a reader, and SQLite releases
    the GIL while it copies. Close it before disposing of the engine."""

    def __init__(self, engine: Engine, interval_s: float = 1.0) -> None:
        if not is_sqlite(engine):
            raise ValueError(f"checkpoints are SQLite's; this engine is {engine.dialect.name}")
        if not interval_s > 0:
            raise ValueError(f"interval_s must be > 0, got {interval_s}")
        self._engine = engine
        self._interval_s = interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="wal-checkpoint", daemon=True)
        self._thread.start()

    def checkpoint(self) -> tuple[int, int]:
        """One PASSIVE checkpoint now: (log frames, frames copied into the database)."""
        with self._engine.connect() as conn:
            row = conn.exec_driver_sql("PRAGMA wal_checkpoint(PASSIVE)").one()
        return int(row[1]), int(row[2])

    def _run(self) -> None:
        while not self._stop.wait(self._interval_s):
            try:
                self.checkpoint()
            except Exception as exc:  # a locked or vanished file: the next tick retries
                log.warning("WAL checkpoint failed: %s", exc)

    def close(self) -> None:
        """Stop the thread after a last checkpoint."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=10.0)
        try:
            self.checkpoint()
        except Exception as exc:
            log.warning("final WAL checkpoint failed: %s", exc)


def alembic_config(engine: Engine) -> Config:
    """An alembic config bound to `engine` (no ini file needed at run time)."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.attributes["engine"] = engine
    return cfg


def upgrade(engine: Engine) -> None:
    """Bring the schema to the newest revision; a no-op on an up-to-date database."""
    command.upgrade(alembic_config(engine), "head")


def session_factory(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)
