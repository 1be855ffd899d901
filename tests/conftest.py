"""Shared fixtures: one throwaway PostgreSQL server for the whole test session, `db_url` on
SQLite and on it, and a migrated `engine` on that URL.

The server is Debian's `postgresql` package (binaries in /usr/lib/postgresql/*/bin), initdb'd
into a temporary directory and started on a free loopback port with fsync off. PostgreSQL
refuses to run as root, so under root (CI) its commands run as the `postgres` system user
through `runuser -u postgres --`. Without the binaries the tests that need it are skipped.
"""

from __future__ import annotations

import glob
import itertools
import logging
import os
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from hypothesis import settings

settings.register_profile("chaos", max_examples=2000)
"""`make chaos`: the scheduler's interleaving properties, many more examples than a test run."""

if TYPE_CHECKING:
    import sqlalchemy as sa

PG_USER = "colony"


@pytest.fixture(autouse=True)
def _root_logging() -> Iterator[None]:
    """An in-process `colony server`, `worker` or `agent` (CliRunner) points the root logger at
    the runner's captured stderr; restore it, or later tests log to a closed stream."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def _pg_bin() -> Path | None:
    """The newest installed PostgreSQL bin directory, or None."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=_major)
    if found:
        return Path(found[-1]).parent
    on_path = shutil.which("initdb")
    return Path(on_path).parent if on_path else None


def _major(path: str) -> int:
    version = Path(path).parent.parent.name
    return int(version) if version.isdigit() else 0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _as_owner(argv: list[str]) -> list[str]:
    """PostgreSQL will not run as root: drop to the `postgres` user when we are root."""
    if os.geteuid() != 0:
        return argv
    if shutil.which("runuser") is None:
        raise RuntimeError("running as root without runuser: cannot start PostgreSQL")
    return ["runuser", "-u", "postgres", "--", *argv]


def _run(argv: list[str]) -> None:
    done = subprocess.run(_as_owner(argv), capture_output=True, text=True, timeout=60)
    if done.returncode:
        raise RuntimeError(f"{argv[0]} failed: {done.stderr.strip() or done.stdout.strip()}")


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[str]:
    """`postgresql+psycopg://colony@127.0.0.1:PORT`: a server for the session (no database)."""
    pytest.importorskip("psycopg", reason="psycopg is not installed")
    bin_dir = _pg_bin()
    if bin_dir is None:
        pytest.skip("PostgreSQL binaries missing: apt-get install -y postgresql")
    if os.geteuid() == 0 and shutil.which("runuser") is None:
        pytest.skip("running as root without runuser: PostgreSQL refuses root")
    root = Path(tempfile.mkdtemp(prefix="colony-pg-"))
    data = root / "data"
    if os.geteuid() == 0:
        shutil.chown(root, user="postgres")
    port = _free_port()
    # --no-sync: a throwaway cluster need not wait for its files to reach the disk.
    _run([str(bin_dir / "initdb"), "--no-sync", "-D", str(data), "-U", PG_USER, "--auth=trust"])
    options = f"-p {port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off"
    options += " -c synchronous_commit=off -c full_page_writes=off -c max_connections=200"
    ctl = [str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(root / "log")]
    _run([*ctl, "-o", options, "-w", "start"])
    try:
        yield f"postgresql+psycopg://{PG_USER}@127.0.0.1:{port}"
    finally:
        subprocess.run(
            _as_owner([*ctl, "-m", "immediate", "stop"]), capture_output=True, timeout=60
        )
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="session")
def postgres_database(postgres_server: str) -> Callable[[], str]:
    """A factory of fresh, empty databases on the session's server: one URL per call."""
    import psycopg

    counter = itertools.count()
    dsn = postgres_server.replace("postgresql+psycopg://", "postgresql://") + "/postgres"

    def fresh() -> str:
        name = f"colony_{os.getpid()}_{next(counter)}"
        with psycopg.connect(dsn, autocommit=True) as conn:
            # PostgreSQL 15+ copies the template through the WAL by default: slower to create,
            # and the session ends deleting hundreds of MB of WAL. A file copy makes the same database.
            copy = " STRATEGY FILE_COPY" if conn.info.server_version >= 150000 else ""
            conn.execute(f'CREATE DATABASE "{name}"{copy}')
        return f"{postgres_server}/{name}"

    return fresh


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A fresh database URL, once on an SQLite file and once on the session's PostgreSQL."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'colony.db'}"
    factory: Callable[[], str] = request.getfixturevalue("postgres_database")
    return factory()


@pytest.fixture
def engine(db_url: str) -> Iterator[sa.Engine]:
    """An engine on `db_url`, migrated to the head revision; disposed after the test."""
    from server.core.db import make_engine, upgrade

    engine = make_engine(db_url)
    upgrade(engine)
    yield engine
    engine.dispose()
