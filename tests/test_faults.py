"""Bad input and faults on the server: NaN and Infinity in any JSON body, requests naming
another host or coming from another site, a damaged or empty SQLite file, a second server on
the same database, and a full disk (SQLite's own SQLITE_FULL through `PRAGMA max_page_count`).

Real uvicorn on free loopback ports, SQLite files in tmp_path, the `colony server` command for
the start-up checks (a process where one must hold the database, in this process where it is
refused); PostgreSQL's lock on the session's throwaway server (tests/conftest.py).
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import sqlalchemy as sa
from typer.testing import CliRunner

from colony.cli import app as cli
from server.core.db import ServerLock, StoreUnusableError, make_engine, upgrade
from server.core.settings import Settings
from tests.helpers import (
    SERVER_START_S,
    TINY,
    completed_run,
    eventually,
    free_port,
    serve,
    serving,
)

JSON = {"content-type": "application/json"}
COLONY = Path(sys.executable).parent / "colony"


@pytest.fixture(scope="module")
def url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A tokenless loopback server without evaluators (runs stay where they are)."""
    db = tmp_path_factory.mktemp("faults") / "colony.db"
    settings = Settings(db_url=f"sqlite:///{db}", port=free_port(), zenoh=False, executors=0)
    with serving(settings) as (base, _):
        yield base


# ------------------------------------------------------------------------- non-finite JSON


@pytest.mark.parametrize(
    ("path", "body", "token"),
    [
        ("/api/runs", '{"fitness": {"k2": NaN}}', "NaN"),
        ("/api/runs", '{"seed": 1, "world": {"dt": -Infinity}}', "-Infinity"),
        ("/api/runs", '{"population": 1e999}', "1e999"),  # Python's parser: inf
        ("/api/robots/evbot-1/controller", '{"run_id": 1, "rank": Infinity}', "Infinity"),
        ("/api/runs/1/pause", "[NaN]", "NaN"),
    ],
)
def test_non_finite_numbers_are_refused_in_every_json_body(
    url: str, path: str, body: str, token: str
) -> None:
    """Whatever the route (one without zenoh behind it, one without a body), before it runs."""
    refused = httpx.post(url + path, content=body, headers=JSON, timeout=30)
    assert refused.status_code == 422
    assert refused.json()["detail"] == (
        f"body: {token} is not a finite number (JSON has no NaN or Infinity; "
        "send a finite number or null)"
    )


def test_finite_and_malformed_bodies_reach_their_route(url: str) -> None:
    with httpx.Client(base_url=url, timeout=30) as client:
        created = client.post("/api/runs", content='{"population": 8, "seed": 1e3}', headers=JSON)
        assert created.status_code == 201 and created.json()["seed"] == 1000
        broken = client.post("/api/runs", content='{"population": ', headers=JSON)
        assert broken.status_code == 422 and "JSON" in broken.json()["detail"]
        assert client.get("/api/runs").status_code == 200


# ------------------------------------------------------------------------------ Host, Origin


def test_a_request_naming_another_host_is_refused(url: str) -> None:
    """DNS rebinding: the attacker's name resolves to 127.0.0.1, so its Host is its name."""
    port = httpx.URL(url).port
    with httpx.Client(base_url=url, timeout=30) as client:
        for method in ("GET", "POST"):
            refused = client.request(method, "/api/runs", headers={"host": f"evil.example:{port}"})
            assert refused.status_code == 403
            assert refused.json()["detail"] == (
                f"Host header 'evil.example:{port}' is not a name of this server: add it to "
                "COLONY_ALLOWED_HOSTS"
            )
        for host in (f"localhost:{port}", f"127.0.0.1:{port}", f"[::1]:{port}", "127.0.0.2"):
            assert client.get("/api/runs", headers={"host": host}).status_code == 200, host
        assert client.get("/healthz", headers={"host": "evil.example"}).status_code == 403


def test_a_mutating_request_from_another_site_is_refused(url: str) -> None:
    """A page on another origin (another port of this host too) cannot create or steer runs;
    the dashboard (its own origin) and the CLI (no Origin) can; reads are not refused."""
    with httpx.Client(base_url=url, timeout=30) as client:
        for origin in ("http://evil.example", "http://127.0.0.1:1", "https://" + url[7:], "null"):
            refused = client.post("/api/runs", json={}, headers={"origin": origin})
            assert refused.status_code == 403, origin
            assert refused.json()["detail"] == (
                f"Origin header {origin!r} is not this server's: cross-site requests refused"
            )
        cross = client.post("/api/runs", headers={"sec-fetch-site": "cross-site"})
        assert cross.status_code == 403
        assert cross.json()["detail"] == (
            "Sec-Fetch-Site header is cross-site: cross-site requests refused"
        )
        assert client.get("/api/runs", headers={"origin": "http://evil.example"}).is_success
        own = {"origin": url, "sec-fetch-site": "same-origin"}
        assert client.post("/api/runs", json={"population": 8}, headers=own).status_code == 201
        assert client.post("/api/runs", json={"population": 8}).status_code == 201


def test_allowed_hosts_add_names_and_star_allows_any(tmp_path: Path) -> None:
    def settings(name: str, hosts: list[str]) -> Settings:
        db = f"sqlite:///{tmp_path / name}"
        return Settings(db_url=db, port=free_port(), zenoh=False, executors=0, allowed_hosts=hosts)

    with serving(settings("a.db", ["Colony.Lab"])) as (base, _):
        port = httpx.URL(base).port
        named = {"host": f"colony.lab:{port}", "origin": f"http://colony.lab:{port}"}
        assert httpx.post(f"{base}/api/runs", json={}, headers=named).status_code == 201
        assert httpx.get(f"{base}/api/runs", headers={"host": "other.lab"}).status_code == 403
    with serving(settings("b.db", ["*"])) as (base, _):
        assert httpx.get(f"{base}/api/runs", headers={"host": "any.name"}).status_code == 200


# ------------------------------------------------------------------ start-up checks (process)


def start_server(db: str, port: int) -> subprocess.Popen[str]:
    argv = [str(COLONY), "server", "--db", db, "--port", str(port), "--no-zenoh"]
    argv += ["--executors", "0"]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def refusal(db: str) -> str:
    """`colony server` on `db` exits with status 1 at once: its stderr. In this process, through
    the CLI's entry point: the refusal comes before the server runs, so a process of its own
    would only add seconds of imports."""
    argv = ["server", "--db", db, "--port", str(free_port()), "--no-zenoh", "--executors", "0"]
    result = CliRunner().invoke(cli, argv)
    assert result.exit_code == 1, (result.stdout, result.stderr, result.exception)
    return result.stderr


@contextmanager
def running_server(db: str) -> Iterator[subprocess.Popen[str]]:
    port = free_port()
    proc = start_server(db, port)
    try:
        with httpx.Client(timeout=1) as probe:

            def healthy() -> bool:
                assert proc.poll() is None, proc.communicate()
                try:
                    return probe.get(f"http://127.0.0.1:{port}/healthz").is_success
                except httpx.TransportError:
                    return False

            assert eventually(healthy, SERVER_START_S)
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
        proc.communicate(timeout=30)


def test_an_empty_database_file_is_refused_in_one_line(tmp_path: Path) -> None:
    db = tmp_path / "colony.db"
    db.touch()
    assert refusal(f"sqlite:///{db}") == (
        f"error: database {db} is empty (0 bytes): restore it from a backup, or delete it to "
        "start a new colony\n"
    )
    assert db.stat().st_size == 0  # left as it was


def test_a_damaged_database_file_is_refused_in_one_line(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.db"
    garbage.write_bytes(b"not a database at all " * 200)
    assert refusal(f"sqlite:///{garbage}") == (
        f"error: database {garbage} is damaged: file is not a database; restore it from a backup\n"
    )
    db = tmp_path / "colony.db"
    engine = make_engine(f"sqlite:///{db}")
    upgrade(engine)
    engine.dispose()
    data = bytearray(db.read_bytes())
    page = 4096
    assert len(data) > 3 * page
    data[2 * page : 3 * page] = b"\xff" * page  # a b-tree page of some table
    db.write_bytes(bytes(data))
    assert refusal(f"sqlite:///{db}") == (
        f"error: database {db} is damaged: Page 3: btreeInitPage() returns error code 11; "
        "restore it from a backup\n"
    )


def test_a_damaged_row_is_an_error_naming_it_and_colony_db_check_finds_it(
    tmp_path: Path,
) -> None:
    """Issue 38: stored blobs carry a checksum verified on read. One flipped bit in a
    generation's population is a 500 naming the run and the generation, never silently served,
    and `colony db check` names the row and exits 1."""
    db = tmp_path / "colony.db"
    url = f"sqlite:///{db}"
    settings = Settings(db_url=url, port=free_port(), zenoh=False)
    with serving(settings) as (base, _):
        run_id = completed_run(base, TINY.model_dump())
    check = ["db", "check", "--db", url]
    clean = CliRunner().invoke(cli, check)
    assert clean.exit_code == 0, clean.output
    assert f"checked {TINY.generations} generations ({TINY.generations} with checksums)" in (
        clean.output
    ) and clean.output.endswith("no damage\n")
    with sqlite3.connect(db) as conn:
        (blob,) = conn.execute(
            "SELECT population FROM generations WHERE run_id = ? AND generation = 1", (run_id,)
        ).fetchone()
        flipped = blob[:-1] + bytes([blob[-1] ^ 1])  # one bit of the last genome weight
        conn.execute(
            "UPDATE generations SET population = ? WHERE run_id = ? AND generation = 1",
            (flipped, run_id),
        )
    why = f"run {run_id} generation 1 population: stored bytes are damaged (checksum mismatch)"
    found = CliRunner().invoke(cli, check)
    assert found.exit_code == 1
    assert found.output.splitlines() == [
        f"damaged: {why}",
        f"checked {TINY.generations} generations ({TINY.generations} with checksums) "
        "and 0 trace batches (0 with checksums): 1 damaged",
    ]
    with serving(Settings(db_url=url, port=free_port(), zenoh=False)) as (base, _):
        served = httpx.get(f"{base}/api/runs/{run_id}/individuals", params={"generation": 1})
        fine = httpx.get(f"{base}/api/runs/{run_id}/individuals", params={"generation": 0})
    assert served.status_code == 500 and served.json()["detail"] == why
    assert fine.status_code == 200
    missing = CliRunner().invoke(cli, ["db", "check", "--db", f"sqlite:///{tmp_path / 'no.db'}"])
    assert missing.exit_code == 1 and "no database at" in missing.output


def test_inconsistent_settings_are_refused_before_the_store_or_a_port_is_touched(
    tmp_path: Path,
) -> None:
    """Issue 38: a lease minimum above the maximum was a traceback from the server's start-up,
    after it had opened the store. It is one usage error, and nothing is touched."""
    db = tmp_path / "colony.db"
    argv = ["server", "--db", f"sqlite:///{db}", "--port", str(free_port()), "--no-zenoh"]
    result = CliRunner().invoke(cli, argv, env={"COLONY_LEASE_MIN_SECONDS": "500"})
    assert result.exit_code == 2, (result.output, result.exception)
    assert "lease_max_s must be >= lease_min_s, got 300.0" in result.output
    assert list(tmp_path.iterdir()) == []


def test_a_second_server_on_the_same_database_is_refused(tmp_path: Path) -> None:
    """The first creates the missing file; a second is refused naming the first's pid, and one
    on a hard link to the file too; once the first dies (kill -9) the lock is gone and a new
    server starts on the same colony."""
    db = tmp_path / "new" / "colony.db"
    url = f"sqlite:///{db}"
    with running_server(url) as first:
        assert db.exists()
        assert refusal(url) == (
            f"error: database {db} is in use by another colony server (pid {first.pid})\n"
        )
        linked = tmp_path / "elsewhere" / "same.db"  # issue 38: a hard link ran a second server
        linked.parent.mkdir()
        os.link(db, linked)
        assert refusal(f"sqlite:///{linked}") == (
            f"error: database {linked} is in use by another colony server that opened it under "
            "another path (a hard link to the same file)\n"
        )
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=30)
    with running_server(url) as again:
        assert again.poll() is None


def test_a_second_server_on_the_same_postgresql_database_is_refused(
    postgres_database: Callable[[], str],
) -> None:
    url = postgres_database()
    first = ServerLock.acquire(url)
    try:
        with pytest.raises(StoreUnusableError) as refused:
            ServerLock.acquire(url)
        assert str(refused.value).endswith(
            f"is in use by another colony server (pid {os.getpid()})"
        )
        ServerLock.acquire(postgres_database()).close()  # another database: its own lock
    finally:
        first.close()
    ServerLock.acquire(url).close()


# --------------------------------------------------------------------------------- disk full


def disk_full_switch(engine: sa.Engine) -> Callable[[bool], None]:
    """While on, every connection the pool hands out may not grow the database file: SQLite
    answers SQLITE_FULL ("database or disk is full"), as on a full disk."""
    full = threading.Event()

    @sa.event.listens_for(engine, "checkout")
    def _limit(dbapi_connection: Any, _record: Any, _proxy: Any) -> None:
        cursor = dbapi_connection.cursor()
        pages = cursor.execute("PRAGMA page_count").fetchone()[0] if full.is_set() else 1 << 30
        cursor.execute(f"PRAGMA max_page_count={pages}")
        cursor.close()

    return lambda on: full.set() if on else full.clear()


def stored_status(db: Path, run_id: int) -> tuple[str, str | None]:
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as conn:
        row = conn.execute("SELECT status, error FROM runs WHERE id = ?", (run_id,)).fetchone()
    return row[0], row[1]


def test_a_full_disk_pauses_runs_visibly_and_healthz_is_degraded_until_it_recovers(
    tmp_path: Path,
) -> None:
    run = {"population": 12, "generations": 100_000, "steps": 10, "trials": 1, "job_size": 12}
    with serve(tmp_path) as served, httpx.Client(base_url=served.url, timeout=30) as client:
        full = disk_full_switch(served.app.state.manager.sessions.kw["bind"])
        run_id = client.post("/api/runs", json=run).json()["id"]

        def view() -> dict[str, Any]:
            shown: dict[str, Any] = client.get(f"/api/runs/{run_id}").json()
            return shown

        assert eventually(lambda: view()["generation"] >= 3)
        full(True)
        assert eventually(lambda: view()["status"] == "paused")
        paused = view()
        assert paused["error"] == (
            "database write failed: OperationalError: database or disk is full"
        )
        assert stored_status(tmp_path / "colony.db", run_id) == ("running", None)  # not yet
        [listed] = client.get("/api/runs").json()
        assert (listed["status"], listed["error"]) == ("paused", paused["error"])
        assert client.get("/api/colony").json()["active"][0]["status"] == "paused"
        health = client.get("/healthz")
        assert health.status_code == 503
        assert health.json()["status"] == "degraded"
        assert health.json()["problems"] == [paused["error"]]
        assert health.json()["stopped"] == []
        still = client.post(f"/api/runs/{run_id}/resume")
        assert still.status_code == 503
        assert still.json()["detail"] == "database unavailable: database or disk is full"
        generation = view()["generation"]
        full(False)
        assert eventually(lambda: client.get("/healthz").status_code == 200)
        assert stored_status(tmp_path / "colony.db", run_id) == ("paused", paused["error"])
        assert view()["generation"] > generation  # the refused one, written now
        resumed = client.post(f"/api/runs/{run_id}/resume")
        assert resumed.status_code == 200
        assert (resumed.json()["status"], resumed.json()["error"]) == ("running", None)
        assert eventually(lambda: view()["generation"] >= generation + 3)
        assert client.post(f"/api/runs/{run_id}/cancel").status_code == 200
