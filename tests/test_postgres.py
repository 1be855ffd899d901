"""The store on PostgreSQL as on SQLite: a lab outgrows SQLite by changing one URL.

Every test takes `db_url` (tests/conftest.py), so it runs once on an SQLite file and once on
the session's throwaway PostgreSQL server. The queue's contract tests of test_server_store.py
are re-run here on a manager built from that URL; a small run goes to completion through the
REST API and must give `evolve`'s best controller bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import httpx
import numpy as np
import pytest
import sqlalchemy as sa
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy.orm import Session

from evorobotics.evolution import evolve
from server import crud
from server.db import alembic_config, make_engine, upgrade
from server.jobs import JobResult
from server.manager import RunManager
from server.models import Base
from server.robot_store import StuckEventRow, TraceRow
from server.settings import Settings
from tests import test_server_api as api
from tests import test_server_store as store
from tests.helpers import free_port

TABLES = store.TABLES | {
    "robot_traces",
    "robot_state",
    "robot_stuck_events",
    "controller_field_stats",
}


@pytest.fixture
def engine(db_url: str) -> Iterator[sa.Engine]:
    engine = make_engine(db_url)
    upgrade(engine)
    yield engine
    engine.dispose()


@pytest.fixture
def manager(engine: sa.Engine) -> RunManager:
    return RunManager(engine, Settings(db_url="unused", lease_seconds=10.0, max_attempts=2))


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


CONTRACT: list[Callable[[RunManager], None]] = [
    store.test_jobs_are_fixed_slices_and_a_duplicate_result_counts_once,
    store.test_result_of_wrong_shape_is_refused,
    store.test_expired_lease_goes_back_and_late_result_is_still_counted_once,
    store.test_runs_share_the_workers_fairly,
    store.test_paused_runs_get_no_jobs_and_failures_fail_the_run,
    store.test_generations_commit_whole_under_concurrent_completion,
    store.test_release_returns_a_lease_at_once_and_counts_follow_the_jobs,
    store.test_a_paused_run_commits_what_is_in_hand_but_leases_nothing_new,
    store.test_results_after_cancel_are_dropped,
    store.test_stored_state_leaves_out_the_population_and_resume_reads_it_back,
    store.test_deferred_write_installs_the_next_generation_first,
    store.test_cancel_writes_the_told_generation_before_cancelling,
    store.test_a_failed_evaluation_is_stored_as_null_ranks_last_and_the_run_goes_on,
]


@pytest.mark.parametrize("contract", CONTRACT, ids=lambda f: f.__name__.removeprefix("test_"))
def test_job_queue_contract(manager: RunManager, contract: Callable[[RunManager], None]) -> None:
    contract(manager)


def test_restart_resumes_from_the_store(engine: sa.Engine) -> None:
    """A second manager on the same database (a restarted server) finishes `evolve`'s run."""
    settings = Settings(db_url="unused", lease_seconds=10.0, max_attempts=2)
    first = RunManager(engine, settings)
    run_id = first.create_run(store.TINY)
    for _ in range(4):
        item = store._evaluate(first, "w", 0.0)
        assert item is not None and first.queue.complete(*item)
    second = RunManager(engine, settings)
    second.recover()
    while (item := store._evaluate(second, "w", 0.0)) is not None:
        assert second.queue.complete(*item) is True
    assert second.best(run_id) == evolve(store.TINY).best.sha256


@pytest.mark.slow
def test_small_run_completes_through_the_rest_api(db_url: str) -> None:
    with api.serving(Settings(db_url=db_url, port=free_port(), zenoh=False)) as (url, _):
        api.test_small_run_completes_and_matches_evolve(url)
        assert httpx.get(f"{url}/healthz", timeout=5).is_success


def test_fitness_nan_round_trips_as_null(engine: sa.Engine) -> None:
    """A failed (NaN) evaluation reads back as None on both stores, and never reaches a float
    column (PostgreSQL would store NaN there, SQLite NULL)."""
    manager = RunManager(engine, Settings(db_url="unused"))
    run_id = manager.create_run(store.SMALL)
    for _ in range(3):
        done = store._evaluate(manager, "w", 0.0)
        assert done is not None
        key, result = done
        fitness = np.full_like(result.fitness, np.nan) if key.index == 1 else result.fitness
        manager.queue.complete(key, JobResult(fitness, result.components))
    with Session(engine) as session:
        ranked = crud.ranked(session, run_id=run_id, generation=0)[0]
        best = crud.get_run(session, run_id=run_id)
    assert [ranked.fitness_of(r) for r in range(len(ranked))].count(None) == 5
    assert best is not None and best.best_fitness is not None


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
    """The deferred write must not let a run evolve on in memory while the store is read-only:
    it stops leasing, is paused with `error` once writable, and resumes to `evolve`'s result."""
    refuse = _refuse_writes(engine)
    manager = RunManager(engine, Settings(db_url="unused", lease_seconds=10.0))
    run_id = manager.create_run(store.TINY)
    while (item := store._evaluate(manager, "w", 0.0)) is not None and item[0].generation == 0:
        manager.queue.complete(*item, defer=True)
    manager.queue.flush()
    assert item is not None  # generation 1's first job, leased before the store went read-only
    refuse(True)
    manager.queue.complete(*item, defer=True)
    while (item := store._evaluate(manager, "w", 0.0)) is not None and item[0].generation == 1:
        manager.queue.complete(*item, defer=True)  # the rest of generation 1
    assert item is not None  # as the dispatcher does, generation 2 went out before the write
    with pytest.raises(sa.exc.DBAPIError):
        manager.queue.flush()
    assert manager.queue.lease("w", 0.0) is None  # stopped: no more of generation 2
    assert manager.queue.complete(*item, defer=True) is True  # what is in hand still counts
    manager.settle_write_failures()  # still read-only: nothing changes, nothing raises
    assert manager.queue.unwritten() == 1
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation) == ("running", 1)
    refuse(False)
    manager.settle_write_failures()
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation) == ("paused", 2)
        assert run.error is not None and "database write failed" in run.error
    assert manager.queue.lease("w", 0.0) is None
    manager.resume(run_id)
    while (item := store._evaluate(manager, "w", 0.0)) is not None:
        assert manager.queue.complete(*item) is True
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.error) == ("completed", None)
    assert manager.best(run_id) == evolve(store.TINY).best.sha256
