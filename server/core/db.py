"""Engine factory and schema migration: the database a lab keeps across upgrades; the checks a
server makes before it uses one (an intact SQLite file, no other server on it)."""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import sqlite3
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import NullPool

from server.core.errors import ServerError

log = logging.getLogger(__name__)

MIGRATIONS = Path(__file__).resolve().parent.parent / "migrations"

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


class StoreUnusableError(ServerError):
    """The database cannot be served (damaged, empty by accident, or in use by another server);
    the message is one line for the operator, naming the database and the problem."""

    status_code = 503


def sqlite_path(url: str) -> Path | None:
    """The file of an SQLite URL; None for any other database."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite" or parsed.database in (None, "", ":memory:"):
        return None
    return Path(parsed.database).expanduser()


def check_sqlite_file(url: str) -> None:
    """StoreUnusableError for an existing SQLite file that is empty (0 bytes: never a colony a
    server made, which starts with its schema) or fails `PRAGMA quick_check`; a missing file
    is fine (a new colony). quick_check reads every page once, without the index cross-checks
    of a full integrity_check."""
    path = sqlite_path(url)
    if path is None or not path.exists():
        return
    if path.stat().st_size == 0:
        raise StoreUnusableError(
            f"database {path} is empty (0 bytes): restore it from a backup, or delete it to "
            "start a new colony"
        )
    problems: list[str]
    try:
        with contextlib.closing(
            sqlite3.connect(f"{path.resolve().as_uri()}?mode=rw", uri=True)
        ) as conn:
            rows = [str(row[0]) for row in conn.execute("PRAGMA quick_check")]
        # a row may hold several lines, under a "*** in database main ***" heading
        problems = [
            line.strip()
            for row in rows
            for line in row.splitlines()
            if line.strip() and not line.startswith("***")
        ]
    except sqlite3.Error as exc:
        problems = [str(exc)]
    if problems != ["ok"]:
        problems = problems or ["quick_check gave no answer"]
        more = f" (and {len(problems) - 1} more problems)" if len(problems) > 1 else ""
        raise StoreUnusableError(
            f"database {path} is damaged: {problems[0]}{more}; restore it from a backup"
        )


PG_LOCK_KEY = (0x436F6C6F, 0x6E790001)
"""The session advisory lock (two int4 keys) a server holds on its PostgreSQL database."""


class ServerLock:
    """Held for the life of one server so that a second on the same database is refused: on
    an SQLite file, an exclusive `flock` on `FILE.lock` beside it (which holds the holder's
    pid, for the refusal's message) and one on the file itself, so on its inode whatever path
    or hard link names it (SQLite's own locks are POSIX record locks, which flock does not
    touch); the kernel drops both when the process dies, even by kill -9. On PostgreSQL, a
    session advisory lock (dropped with the session). Other databases get no lock. Released
    after the engine is disposed: closing a descriptor of the file drops the process's POSIX
    locks on it."""

    def __init__(self, release: Callable[[], None]) -> None:
        self._release: Callable[[], None] | None = release

    @classmethod
    def acquire(cls, url: str) -> ServerLock:
        """The lock of the database at `url`; StoreUnusableError naming the holder's pid when
        another server holds it."""
        path = sqlite_path(url)
        if path is not None:
            return cls._flock(path)
        if make_url(url).get_backend_name() == "postgresql":
            return cls._advisory(url)
        return cls(lambda: None)

    @classmethod
    def _flock(cls, database: Path) -> ServerLock:
        lock = database.with_name(database.name + ".lock")
        try:
            lock.parent.mkdir(parents=True, exist_ok=True)
            # SQLite writes its journal beside the file: the directory itself must be writable
            writable = os.access(lock.parent, os.W_OK | os.X_OK)
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644) if writable else -1
            reason = "not writable"
        except FileExistsError:
            fd, reason = -1, "a file is in the way of a directory"
        except OSError as exc:
            fd, reason = -1, exc.strerror or str(exc)
        if fd < 0:
            raise StoreUnusableError(
                f"cannot write the database's directory {lock.parent.absolute()}: {reason}; "
                "choose a writable one with --db sqlite:///DIR/colony.db"
            )
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise StoreUnusableError(
                f"database {database} is in use by another colony server (pid {holder})"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        try:
            if not database.exists():  # a new store: a valid empty one, so its inode is locked
                with contextlib.closing(sqlite3.connect(database)) as new:
                    new.execute("PRAGMA journal_mode=WAL")  # writes the header
            held = os.open(database, os.O_RDWR)
            fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(held)
            os.close(fd)
            raise StoreUnusableError(
                f"database {database} is in use by another colony server that opened it under "
                "another path (a hard link to the same file)"
            ) from None
        except (OSError, sqlite3.Error) as exc:
            os.close(fd)
            why = (exc.strerror if isinstance(exc, OSError) else None) or str(exc)
            raise StoreUnusableError(f"cannot open the database {database}: {why}") from None

        def release() -> None:
            os.close(held)
            os.close(fd)

        return cls(release)

    @classmethod
    def _advisory(cls, url: str) -> ServerLock:
        name = f"colony-server {os.getpid()}"
        engine = create_engine(url, poolclass=NullPool, connect_args={"application_name": name})
        conn = engine.connect()
        keys = {"a": PG_LOCK_KEY[0], "b": PG_LOCK_KEY[1]}
        if conn.scalar(
            text("SELECT pg_try_advisory_lock(CAST(:a AS integer), CAST(:b AS integer))"), keys
        ):
            conn.commit()  # the lock is the session's: it outlives the transaction

            def release() -> None:
                conn.close()
                engine.dispose()

            return cls(release)
        holder = conn.scalar(
            text(
                "SELECT a.application_name FROM pg_locks l JOIN pg_stat_activity a "
                "ON a.pid = l.pid WHERE l.locktype = 'advisory' AND l.granted "
                "AND l.classid = :a AND l.objid = :b AND l.objsubid = 2"
            ),
            keys,
        )
        conn.close()
        engine.dispose()
        pid = str(holder).removeprefix("colony-server ") if holder else "unknown"
        raise StoreUnusableError(
            f"database {make_url(url).render_as_string(hide_password=True)} is in use by "
            f"another colony server (pid {pid})"
        )

    def close(self) -> None:
        """Release the lock (also released when the process exits)."""
        if self._release is not None:
            self._release()
            self._release = None
