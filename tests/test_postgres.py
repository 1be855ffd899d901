"""The store on PostgreSQL as on SQLite: a lab outgrows SQLite by changing one URL.

Every test takes `db_url` (tests/conftest.py), so it runs once on an SQLite file and once on
the session's throwaway PostgreSQL server. The job path's contract tests in test_server_store.py
take `db_url` themselves; here are the migrations, a restart, a refused write, and a small run goes to completion through the
REST API and must give `evolve`'s best controller bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import httpx
import pytest
import sqlalchemy as sa
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy.orm import Session

from evorobotics.evolution import evolve
from server.core.db import alembic_config, upgrade
from server.core.models import Base
from server.core.settings import Settings
from server.robots.store import StuckEventRow, TraceRow
from server.runs import crud
from server.runs.lifecycle import RunManager
from tests.helpers import TINY, check_small_run, drain, evaluated, free_port, serving

TABLES = {
    "runs",
    "generations",
    "controllers",
    "robots",
    "robot_traces",
    "robot_state",
    "robot_stuck_events",
    "controller_field_stats",
}


BASE: dict[str, Any] = {"db_url": "unused", "max_attempts": 2, "span_below_seconds": 0.0}
"""No spans: the cut of each generation follows the live workers only (not their speeds)."""


def test_migrations_go_up_down_and_up_again(engine: sa.Engine) -> None:
    """Every revision, the robot tables included, applies and reverts on both back ends."""
    names = set(sa.inspect(engine).get_table_names())
    assert names >= TABLES, sorted(TABLES - names)
    cfg = alembic_config(engine)
    command.downgrade(cfg, "base")
    assert set(sa.inspect(engine).get_table_names()) <= {"alembic_version"}
    upgrade(engine)
    upgrade(engine)
    with engine.connect() as conn:
        versions = conn.execute(sa.text("SELECT version_num FROM alembic_version")).all()
    assert versions == [(ScriptDirectory.from_config(cfg).get_current_head(),)]


def test_the_migrations_build_exactly_the_schema_of_the_models(engine: sa.Engine) -> None:
    """`upgrade()` on a fresh database gives the tables, columns, types, nullability, indexes,
    keys and server defaults the models declare: a model change without a revision fails here."""
    with engine.connect() as conn:
        context = MigrationContext.configure(
            conn, opts={"compare_type": True, "compare_server_default": True}
        )
        assert compare_metadata(context, Base.metadata) == []


def test_robot_tables_keep_64_bit_steps_and_bytes(engine: sa.Engine) -> None:
    """Robot step counters outgrow 32 bits in a long-lived lab; blobs come back byte-exact."""
    blob = bytes(range(256))
    big = 2**40 + 7
    with Session(engine) as session, session.begin():
        session.add(
            TraceRow(
                robot_id="r1", boot=1, first=big, last=big + 9, count=10, controllers="[]",
                steps=blob, whiskers=blob, motors=blob, controller=blob, fresh=blob,
            )
        )  # fmt: skip
        session.add(StuckEventRow(robot_id="r1", reason="rotation", step=big))
    with Session(engine) as session:
        trace = session.scalars(sa.select(TraceRow)).one()
        event = session.scalars(sa.select(StuckEventRow)).one()
    assert (trace.first, trace.steps, trace.fresh) == (big, blob, blob)
    assert event.step == big and event.id is not None


def test_restart_resumes_from_the_store(engine: sa.Engine) -> None:
    """A second manager on the same database (a restarted server) finishes `evolve`'s run."""
    first = RunManager(engine, Settings(**BASE))
    run_id = first.create_run(TINY)
    for _ in range(4):  # generation 0's three jobs, then generation 1 (one job: one worker)
        result = evaluated(first, "w")
        assert result is not None and first.scheduler.settle(result).accepted
        first.flush()
    second = RunManager(engine, Settings(**BASE))
    second.recover()
    with Session(engine) as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation) == ("running", 2)
    drain(second)
    assert second.best(run_id).sha256 == evolve(TINY).best.sha256


@pytest.mark.slow
def test_small_run_completes_through_the_rest_api(db_url: str) -> None:
    with serving(Settings(db_url=db_url, port=free_port(), zenoh=False)) as (url, _):
        check_small_run(url)
        assert httpx.get(f"{url}/healthz", timeout=5).is_success


def _refuse_writes(engine: sa.Engine) -> Callable[[bool], None]:
    """A switch that makes the database read-only for every connection the pool hands out:
    SQLite's `query_only` and PostgreSQL's read-only transactions give the real errors."""
    refusing = [False]
    sqlite = engine.dialect.name == "sqlite"

    @sa.event.listens_for(engine, "checkout")
    def _mode(dbapi_connection: Any, _record: Any, _proxy: Any) -> None:
        cursor = dbapi_connection.cursor()
        if sqlite:
            cursor.execute(f"PRAGMA query_only={int(refusing[0])}")
        else:
            cursor.execute(f"SET default_transaction_read_only = {'on' if refusing[0] else 'off'}")
            dbapi_connection.commit()
        cursor.close()

    def switch(on: bool) -> None:
        refusing[0] = on

    return switch


def test_a_store_that_refuses_writes_stops_the_run_and_resume_is_bit_identical(
    engine: sa.Engine,
) -> None:
    """Told generations must not let a run evolve on in memory while the store is read-only:
    a refused write stops its leasing (what is leased still counts), is retried at every
    flush, and once in, the run is paused with `error`; it resumes to `evolve`'s result."""
    refuse = _refuse_writes(engine)
    manager = RunManager(engine, Settings(**BASE))
    run_id = manager.create_run(TINY)
    for worker in ("w", "w", "w"):  # generation 0: three jobs (no worker known at its cut)
        result = evaluated(manager, worker)
        assert result is not None and result.key.generation == 0
        assert manager.scheduler.settle(result).accepted
    manager.flush()
    refuse(True)
    result = evaluated(manager, "a")  # generation 1: one job ("w" was the one live worker)
    assert result is not None and result.key.generation == 1
    assert manager.scheduler.settle(result).accepted
    held = evaluated(manager, "b")  # generation 2 (cut for w and a) goes out before the write
    assert held is not None and (held.key.generation, held.start, held.stop) == (2, 0, 3)
    with pytest.raises(sa.exc.DBAPIError):
        manager.flush()
    assert manager.scheduler.lease("c") is None  # stopped: no more of generation 2
    assert manager.scheduler.settle(held).accepted is True  # what is in hand still counts
    with pytest.raises(sa.exc.DBAPIError):
        manager.flush()  # still read-only: retried, refused again
    with Session(engine) as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation, run.error) == ("running", 1, None)
    refuse(False)
    manager.flush()
    with Session(engine) as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation) == ("paused", 2)
        assert run.error is not None and "database write failed" in run.error
    assert manager.scheduler.lease("c") is None
    manager.resume(run_id)
    drain(manager)
    with Session(engine) as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.error) == ("completed", None)
    assert manager.best(run_id).sha256 == evolve(TINY).best.sha256
