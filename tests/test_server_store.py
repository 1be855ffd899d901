"""The store: migrations, population frames, GA state round trip, the job path's contract
through the run manager (scheduler leases and results, the manager's writes), and genomes
stored once per run (Eq 11's copies point to the generation holding their bytes).

The manager-driven tests take `db_url` (tests/conftest.py): they run once on an SQLite file and
once on the session's PostgreSQL. They call `manager.flush()` themselves (no writer thread).
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import sqlalchemy as sa
from alembic import command
from alembic.script import ScriptDirectory
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from sqlalchemy.orm import Session

from evorobotics.evaluate import evaluate
from evorobotics.evolution import RunLoop, evaluate_population, evolve
from evorobotics.ga import GAParams, GAState, ask, ga_rng, init, tell
from evorobotics.layout import layout
from schemas.run import GAConfig, RunConfig
from schemas.wire import Job, JobKey, Result, decode_frame, encode_frame, genome_digest
from server.core.db import Checkpointer, alembic_config, make_engine, upgrade
from server.core.errors import NotFoundError, ServerError
from server.core.integrity import unseal
from server.core.models import Generation
from server.core.settings import Settings
from server.robots.replacement import ranked_document
from server.runs import crud
from server.runs.evaluation import run_job
from server.runs.lifecycle import RunManager
from server.runs.population import (
    PopulationError,
    Stored,
    decode,
    decode_state,
    encode,
    encode_state,
)
from tests.helpers import TINY, WAIT, drain, evaluated, eventually

TABLES = {"runs", "generations", "controllers", "robots"}
SMALL = RunConfig(population=12, generations=3, steps=10, trials=2, job_size=5)
BASE: dict[str, Any] = {
    "db_url": "unused",
    "max_attempts": 2,
    "span_below_seconds": 0.0,  # no spans unless a test asks: cuts do not follow measured speeds
    "lease_min_seconds": 0.05,
    "lease_unknown_seconds": 0.5,  # leases expire only when a test calls expire()
    "spot_checks": 0,  # results of zero fitness stand in for evaluation (test_spotcheck.py)
}


@pytest.fixture
def make_manager(engine: sa.Engine) -> Callable[..., RunManager]:
    """Managers on the test's database, with BASE settings updated by keyword."""

    def make(**overrides: Any) -> RunManager:
        return RunManager(engine, Settings(**{**BASE, **overrides}))

    return make


@pytest.fixture
def manager(make_manager: Callable[..., RunManager]) -> RunManager:
    """A manager without executors or writer thread: tests lease, settle and flush by hand."""
    return make_manager()


def test_fresh_database_gets_every_table_and_upgrade_is_idempotent(tmp_path: Path) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'sub' / 'c.db'}")
    upgrade(engine)
    upgrade(engine)
    inspector = sa.inspect(engine)
    assert set(inspector.get_table_names()) >= TABLES
    with engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() == 10_000
        versions = conn.exec_driver_sql("SELECT version_num FROM alembic_version").all()
    head = ScriptDirectory.from_config(alembic_config(engine)).get_current_head()
    assert versions == [(head,)]
    engine.dispose()


def test_memory_sqlite_is_refused() -> None:
    with pytest.raises(ValueError, match="SQLite file"):
        make_engine("sqlite://")


@settings(max_examples=50, deadline=None)
@given(
    n=st.integers(0, 6),
    trials=st.integers(1, 3),
    width=st.integers(1, 5),
    checkpoint=st.booleans(),
    with_descriptors=st.booleans(),
    data=st.data(),
)
def test_a_population_frame_round_trips_bits(
    n: int, trials: int, width: int, checkpoint: bool, with_descriptors: bool, data: st.DataObject
) -> None:
    """A generation between checkpoints (fitness, descriptors or not) and a checkpoint (with
    genomes and components, stored compressed) read back bit for bit: NaN fitness (a failed
    evaluation), NaN payloads and -0.0 included."""
    floats = st.floats(width=64)
    stored = Stored(
        fitness=data.draw(hnp.arrays(np.float64, n, elements=floats)),
        descriptors=data.draw(hnp.arrays(np.float64, (n, 4), elements=st.floats(0, 1)))
        if with_descriptors
        else None,
        genomes=data.draw(hnp.arrays(np.float64, (n, width), elements=floats))
        if checkpoint
        else None,
        components=data.draw(hnp.arrays(np.float64, (n, trials, 4), elements=floats))
        if checkpoint
        else None,
    )
    back = decode(encode(stored))
    assert back.checkpoint == checkpoint
    for name in ("fitness", "descriptors", "genomes", "components"):
        value, read = getattr(stored, name), getattr(back, name)
        assert (read is None) == (value is None), name
        if value is not None:
            assert read.shape == value.shape and read.tobytes() == value.tobytes(), name


def test_a_frame_of_another_kind_shape_or_dtype_is_refused() -> None:
    state = init(layout(SMALL.network_spec), GAParams.from_config(SMALL))
    with pytest.raises(PopulationError, match="kind"):
        decode(encode_frame({"kind": "ga-state"}, state.to_arrays()))
    with pytest.raises(PopulationError, match="not a frame"):
        decode(b"EVC1 garbage")
    good = Stored(np.zeros(3), np.zeros((3, 4)), np.zeros((3, 2)), np.zeros((3, 1, 4)))
    assert len(decode(encode(good)).fitness) == 3
    for name, value, match in [
        ("descriptors", np.zeros((3, 2)), "descriptors of"),
        ("genomes", np.zeros((2, 2)), "genomes of"),
        ("components", np.zeros((3, 4)), "components of"),
        ("components", None, "both genomes and components"),
    ]:
        with pytest.raises(PopulationError, match=match):
            decode(encode(dataclasses.replace(good, **{name: value})))  # type: ignore[arg-type]
    header, arrays = decode_frame(encode(good))
    for changed, match in [
        ({**arrays, "fitness": np.zeros(3, dtype=np.int64)}, "population frame of arrays"),
        ({**arrays, "genomes": arrays["genomes"][:-2]}, "packed genomes"),  # truncated
        ({**arrays, "extra": np.zeros(1)}, "population frame of arrays"),
    ]:
        with pytest.raises(PopulationError, match=match):
            decode(encode_frame(header, changed))
    bomb = encode_frame({**header, "packed": {**header["packed"], "genomes": [3, 1]}}, arrays)
    with pytest.raises(PopulationError, match="does not hold"):  # more bytes than its shape
        decode(bomb)
    old = encode_frame({"kind": "population"}, {"index": np.arange(3)})  # before checkpoints
    with pytest.raises(PopulationError, match="'population', expected 'told'"):
        decode(old)


def test_a_damaged_stored_population_is_a_server_error_with_its_place(
    manager: RunManager,
) -> None:
    run_id = _first_generation_written(manager)
    with manager.sessions.begin() as session:
        session.execute(
            sa.update(Generation)
            .where(Generation.run_id == run_id, Generation.generation == 0)
            .values(population=b"EVC1 truncated")
        )
    with manager.sessions() as session, pytest.raises(ServerError) as caught:
        crud.ranked(session, run_id=run_id, generation=0)
    assert "run 1 generation 0: stored population: not a frame" in str(caught.value)
    assert not isinstance(caught.value, NotFoundError)


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**32), st.integers(1, 3))
def test_ga_state_round_trips_through_the_store_encoding(seed: int, generations: int) -> None:
    config = SMALL.model_copy(update={"seed": seed})
    lay, params = layout(config.network_spec), GAParams.from_config(config)
    state = init(lay, params)
    for g in range(generations):
        genomes, state = ask(ga_rng(seed, g), state, params, lay)
        fitness = np.random.default_rng(g).normal(size=config.population)
        state, _ = tell(genomes, fitness, state, params)
    assert state.ranked is not None
    back = decode_state(encode_state(state), ranked=state.ranked)
    for name, value in state.to_arrays().items():
        assert np.array_equal(back.to_arrays()[name], value)
    a, _ = ask(ga_rng(seed, generations), state, params, lay)
    b, _ = ask(ga_rng(seed, generations), back, params, lay)
    assert a.tobytes() == b.tobytes()


def test_background_checkpoint_copies_the_log_that_writes_no_longer_copy(tmp_path: Path) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'c.db'}", background_checkpoint=True)
    upgrade(engine)
    with engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA wal_autocheckpoint").scalar() == 0
    database = tmp_path / "c.db"
    with engine.begin() as conn:
        conn.exec_driver_sql("CREATE TABLE t (x BLOB)")
        conn.exec_driver_sql("INSERT INTO t VALUES (?)", (bytes(1 << 16),))
    assert database.stat().st_size < 1 << 16  # the blob is only in the write-ahead log
    checkpointer = Checkpointer(engine, interval_s=0.05)
    try:
        assert eventually(lambda: database.stat().st_size > 1 << 16, timeout=10.0)
        frames, copied = checkpointer.checkpoint()
        assert copied == frames
    finally:
        checkpointer.close()
        engine.dispose()
    with pytest.raises(ValueError, match="SQLite"):
        Checkpointer(sa.create_engine("postgresql+psycopg://u@localhost/db"))


# the job path: scheduler leases and results, the manager's writes -------------------------------


def _lease(manager: RunManager, worker: str) -> Job:
    job = manager.scheduler.lease(worker)
    assert job is not None, f"no job for {worker}"
    return job


def _fake(job: Job, worker: str, *, start: int | None = None, stop: int | None = None) -> Result:
    """A result of zero fitness for `job` (or for another slice of its generation)."""
    start = job.start if start is None else start
    stop = job.stop if stop is None else stop
    n, trials = stop - start, job.config.trials
    return Result(
        key=job.key,
        worker=worker,
        start=start,
        stop=stop,
        fitness=np.zeros((1, n)),
        components=np.zeros((1, n, trials, 4)),
        descriptors=np.zeros((1, n, 4)),
    )


def _error(job: Job, worker: str, message: str) -> Result:
    return Result(key=job.key, worker=worker, start=job.start, stop=job.stop, error=message)


def _run_row(manager: RunManager, run_id: int) -> tuple[str, int]:
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None
        return run.status, run.generation


def _first_generation_written(manager: RunManager) -> int:
    """A SMALL run with its generation 0 evaluated (its 3 jobs) and written; its id."""
    run_id = manager.create_run(SMALL)
    for _ in range(3):
        result = evaluated(manager, "w")
        assert result is not None and result.key.generation == 0
        assert manager.scheduler.settle(result).accepted
    manager.flush()
    return run_id


def test_generations_are_cut_per_live_worker_and_the_run_matches_evolve(
    manager: RunManager,
) -> None:
    """Generation 0 (no worker known yet) is cut by the run's job_size; a later generation into
    one job per live serving worker (at least job_size each), cut when the one before is told;
    fitness does not depend on the cut."""
    run_id = manager.create_run(SMALL)
    manager.scheduler.join("other-protocol", serving=False)  # never counted
    sched = manager.scheduler

    def settle(job: Job, worker: str) -> tuple[int, int]:
        assert sched.settle(run_job(job, worker)).accepted
        return job.start, job.stop

    a, b = _lease(manager, "a"), _lease(manager, "b")  # distinct names: held at once
    first = [settle(a, "a"), settle(_lease(manager, "a"), "a"), settle(b, "b")]
    a, b = _lease(manager, "a"), _lease(manager, "b")
    assert sched.leave("b") == [b.key]  # gone: its job returns, generation 2 is one job
    second = [settle(a, "a"), settle(_lease(manager, "a"), "a")]
    third = [settle(_lease(manager, "a"), "a")]
    manager.flush()
    cuts = [sorted(first), sorted(second), third]
    assert cuts == [[(0, 5), (5, 10), (10, 12)], [(0, 6), (6, 12)], [(0, 12)]]
    assert _run_row(manager, run_id) == ("running", SMALL.generations - 1)  # its champion's
    drain(manager, "a")
    assert _run_row(manager, run_id) == ("completed", SMALL.generations)
    assert manager.best(run_id).sha256 == evolve(SMALL).best.sha256


def test_jobs_are_fixed_slices_and_a_duplicate_result_counts_once(manager: RunManager) -> None:
    run_id = manager.create_run(SMALL)
    workers = ["w0", "w1", "w2"]
    leased = [_lease(manager, w) for w in workers]
    assert [(j.start, j.stop) for j in leased] == [(0, 5), (5, 10), (10, 12)]
    assert manager.scheduler.lease("w3") is None
    results = [run_job(job, w) for job, w in zip(leased, workers, strict=True)]
    assert manager.scheduler.settle(results[0]).accepted is True
    duplicate = manager.scheduler.settle(results[0])  # acknowledged, dropped
    assert (duplicate.accepted, duplicate.key) == (False, leased[0].key)
    for result in results[1:]:
        assert manager.scheduler.settle(result).accepted is True
    assert manager.scheduler.settle(results[2]).accepted is False  # late: generation told
    manager.flush()
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None
        assert (run.generation, run.evaluations) == (1, SMALL.population)
        ranked = crud.ranked(session, run_id=run_id, generation=0)[0]
    assert sorted(ranked.index.tolist()) == list(range(SMALL.population))
    values = ranked.fitness.tolist()
    assert np.isfinite(values).all() and values == sorted(values, reverse=True)
    assert manager.scheduler.totals()["duplicates_dropped"] == 2


def test_a_result_for_another_slice_is_dropped_and_the_lease_stays(manager: RunManager) -> None:
    manager.create_run(SMALL)
    job = _lease(manager, "w")
    assert (job.start, job.stop) == (0, 5)
    with pytest.raises(ValueError, match="fitness"):  # arrays must fit the slice they name
        Result(
            key=job.key,
            worker="w",
            start=0,
            stop=5,
            fitness=np.zeros((1, 2)),
            components=np.zeros((1, 2, 2, 4)),
            descriptors=np.zeros((1, 2, 4)),
        )
    assert manager.scheduler.settle(_fake(job, "w", start=5, stop=10)).accepted is False
    assert manager.scheduler.settle(_fake(job, "other")).accepted is False  # not its lease
    assert manager.scheduler.settle(_fake(job, "w")).accepted is True


def test_an_expired_lease_goes_back_and_only_its_new_holder_s_result_counts(
    manager: RunManager,
) -> None:
    manager.create_run(SMALL.model_copy(update={"job_size": 12}))
    first = _lease(manager, "slow")
    assert manager.scheduler.lease("other") is None
    assert manager.scheduler.expire() == 0  # its deadline has not passed
    deadline = manager.scheduler.next_deadline()
    assert deadline is not None
    assert eventually(lambda: manager.scheduler.now() >= deadline, timeout=10.0)
    assert manager.scheduler.expire() == 1
    slow = run_job(first, "slow")
    assert manager.scheduler.settle(slow).accepted is False  # no lease held: dropped
    second = _lease(manager, "fast")
    assert second.key == first.key
    assert manager.scheduler.settle(slow).accepted is False  # the lease is fast's now
    assert manager.scheduler.settle(run_job(second, "fast")).accepted is True
    assert manager.scheduler.totals() == {
        "leased": 2,
        "done": 1,
        "requeued": 1,
        "duplicates_dropped": 2,
    }


def test_runs_share_the_workers_fairly(manager: RunManager) -> None:
    a = manager.create_run(SMALL.model_copy(update={"job_size": 3}))
    b = manager.create_run(SMALL.model_copy(update={"job_size": 3, "seed": 1}))
    order = [_lease(manager, f"w{i}").key.run_id for i in range(6)]
    assert order == [a, b, a, b, a, b]


def test_paused_runs_get_no_jobs_and_a_workers_error_fails_nothing(manager: RunManager) -> None:
    """An error result returns its job; with no other worker to take it the server evaluates
    it itself, and the run completes (only the server's own evaluation failing fails it)."""
    run_id = manager.create_run(SMALL)
    manager.pause(run_id)
    assert manager.scheduler.lease("w") is None
    manager.resume(run_id)
    job = _lease(manager, "w")
    assert job.key.index == 0 and job.key.generation == 0
    ack = manager.scheduler.settle(_error(job, "w", "boom"))
    assert (ack.accepted, ack.reason) == (True, "error recorded")

    def completed() -> bool:
        while (other := evaluated(manager, "w")) is not None:  # every other job, the run's end
            assert other.key != job.key and manager.scheduler.settle(other).accepted
        manager.flush()
        return _run_row(manager, run_id) == ("completed", SMALL.generations)

    assert eventually(completed, WAIT)
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and run.error is None


def test_generations_commit_whole_under_concurrent_results_and_writes(
    manager: RunManager,
) -> None:
    """Two threads lease, settle and flush at once; every committed generation is complete."""
    run_id = manager.create_run(SMALL.model_copy(update={"job_size": 2}))
    errors: list[BaseException] = []

    def work(name: str) -> None:
        try:
            while (result := evaluated(manager, name)) is not None:
                manager.scheduler.settle(result)
                manager.flush()
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(f"t{i}",)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors and not any(t.is_alive() for t in threads)
    assert _run_row(manager, run_id) == ("completed", SMALL.generations)
    with manager.sessions() as session:
        for g in range(SMALL.generations):
            assert len(crud.ranked(session, run_id=run_id, generation=g)[0]) == 12
    assert manager.best(run_id).sha256 == evolve(SMALL).best.sha256


def test_leases_return_when_a_worker_leaves_or_asks_again_and_counts_follow(
    manager: RunManager,
) -> None:
    manager.create_run(SMALL)
    first = _lease(manager, "gone")
    second = _lease(manager, "w")
    again = _lease(manager, "w")  # asking again: its reply was lost, the same job comes back
    assert again.key == second.key
    assert manager.scheduler.counts() == {"pending": 1, "leased": 2, "done": 0}
    assert manager.scheduler.settle(run_job(again, "w")).accepted is True
    assert manager.scheduler.leave("gone") == [first.key]
    assert manager.scheduler.leave("gone") == []
    assert manager.scheduler.counts() == {"pending": 2, "leased": 0, "done": 1}
    assert _lease(manager, "w").key == first.key
    assert manager.scheduler.totals()["requeued"] == 2


def test_a_paused_run_settles_what_is_in_hand_but_leases_nothing_new(
    manager: RunManager,
) -> None:
    run_id = manager.create_run(SMALL.model_copy(update={"job_size": 12}))
    result = evaluated(manager, "w")
    assert result is not None
    manager.pause(run_id)
    assert manager.scheduler.settle(result).accepted is True
    assert manager.scheduler.lease("w") is None
    manager.flush()
    assert _run_row(manager, run_id) == ("paused", 1)
    manager.resume(run_id)
    assert _lease(manager, "w").key.generation == 1


def test_results_after_cancel_are_dropped(manager: RunManager) -> None:
    run_id = manager.create_run(SMALL)
    result = evaluated(manager, "w")
    assert result is not None
    manager.cancel(run_id)
    assert manager.scheduler.settle(result).accepted is False
    assert manager.scheduler.lease("w") is None
    assert manager.scheduler.counts() == {"pending": 0, "leased": 0, "done": 0}


def test_a_checkpoint_s_state_leaves_out_the_population_and_replay_reads_it_back(
    make_manager: Callable[..., RunManager],
) -> None:
    manager = make_manager(checkpoint_every=1)
    run_id = _first_generation_written(manager)
    with manager.sessions() as session:
        stored = crud.get_generation(session, run_id=run_id, generation=0)
        run = crud.get_run(session, run_id=run_id)
        assert stored is not None and stored.state is not None and run is not None
        arrays = decode_frame(unseal(stored.state, "its GA state"))[1]
        assert "ranked" not in arrays and "ranked_fitness" in arrays
        state = crud.replay(session, run=run, config=SMALL, generation=1).state
    params = GAParams.from_config(SMALL)
    lay = layout(SMALL.network_spec)
    genomes, _ = ask(ga_rng(SMALL.seed, 0), init(lay, params), params, lay)
    fitness = np.concatenate(
        [evaluate(SMALL, 0, genomes[a:b]).fitness for a, b in ((0, 5), (5, 10), (10, 12))]
    )
    expected, _ = tell(genomes, fitness, init(lay, params), params)
    assert expected.ranked is not None and state.ranked is not None
    assert state.ranked.tobytes() == expected.ranked.tobytes()


def test_the_next_generation_is_leased_before_the_told_one_is_written(
    manager: RunManager,
) -> None:
    """Settling a generation's last job asks the next at once; the store gets the told one at
    `flush`, exactly once."""
    run_id = manager.create_run(SMALL)
    results = [evaluated(manager, w) for w in ("w0", "w1", "w2")]
    for result in results:
        assert result is not None and manager.scheduler.settle(result).accepted
    assert _lease(manager, "w0").key.generation == 1
    with manager.sessions() as session:
        assert crud.get_generation(session, run_id=run_id, generation=0) is None
    assert _run_row(manager, run_id) == ("running", 0)
    manager.flush()
    manager.flush()
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.generation, run.evaluations) == (1, SMALL.population)
        assert len(crud.ranked(session, run_id=run_id, generation=0)[0]) == 12


def test_flush_writes_the_told_generations_in_one_transaction(
    manager: RunManager, engine: sa.Engine
) -> None:
    """Generations told between two flushes go into one commit; `stop` writes what is left
    (no writer thread here); the last generation, with its champion, completes the run."""
    whole = SMALL.model_copy(update={"job_size": SMALL.population, "generations": 4})
    run_id = manager.create_run(whole)
    commits: list[int] = []

    def tell_one() -> None:
        result = evaluated(manager, "w")
        assert result is not None and manager.scheduler.settle(result).accepted

    def count(_conn: sa.Connection) -> None:
        commits.append(1)

    tell_one()
    tell_one()
    assert _run_row(manager, run_id) == ("running", 0)
    sa.event.listen(engine, "commit", count)
    try:
        manager.flush()
        assert len(commits) == 1
        manager.flush()  # nothing told: no transaction
        assert len(commits) == 1
    finally:
        sa.event.remove(engine, "commit", count)
    assert _run_row(manager, run_id) == ("running", 2)
    tell_one()
    manager.stop()
    assert _run_row(manager, run_id) == ("running", 3)
    tell_one()
    manager.flush()
    assert _run_row(manager, run_id) == ("running", 3)  # its champion's stages are jobs
    drain(manager)
    assert _run_row(manager, run_id) == ("completed", 4)
    assert manager.best(run_id).sha256 == evolve(whole).best.sha256


def test_cancel_writes_the_told_generation_before_cancelling(manager: RunManager) -> None:
    run_id = manager.create_run(SMALL.model_copy(update={"job_size": 12}))
    result = evaluated(manager, "w")
    assert result is not None and manager.scheduler.settle(result).accepted
    manager.cancel(run_id)
    assert _run_row(manager, run_id) == ("cancelled", 1)
    assert manager.scheduler.lease("w") is None


def test_listeners_hear_of_leasable_jobs_until_removed(manager: RunManager) -> None:
    calls: list[int] = []

    def listener() -> None:
        calls.append(1)

    manager.scheduler.add_listener(listener)
    manager.create_run(SMALL)
    assert len(calls) == 1  # the run's first generation
    job = _lease(manager, "w")
    assert len(calls) == 1  # leasing announces nothing
    assert manager.scheduler.leave("w") == [job.key]
    assert len(calls) == 2  # its job returned
    manager.scheduler.remove_listener(listener)
    job = _lease(manager, "w")
    assert manager.scheduler.leave("w") == [job.key]
    assert len(calls) == 2


# spans: a fast worker evolves the following generations itself ----------------------------------

SPANNED = RunConfig(population=6, generations=6, steps=5, trials=1, job_size=2, seed=3)
FAST = 1000.0
"""Robot-steps/s: a SPANNED generation (30 robot-steps) in 0.03 s, so with span_seconds 0.1 a
span of 3 generations."""
SPANS = {"span_below_seconds": 0.1, "span_seconds": 0.1}


def _span_result(loop: RunLoop, job: JobKey, worker: str, k: int = 1) -> Result:
    """What a span's worker sends for `job`: its loop's next `k` generations evaluated and
    told, with the digest of each generation's genomes."""
    key = job.at(loop.generation)
    fitness, components, descriptors, digests = [], [], [], []
    for _ in range(k):
        genomes = loop.ask()
        f, c, d = evaluate_population(loop.config, loop.generation, genomes)
        loop.tell(f, c, d)
        fitness.append(f)
        components.append(c)
        descriptors.append(d)
        digests.append(genome_digest(genomes))
    return Result(
        key=key,
        worker=worker,
        start=0,
        stop=loop.config.population,
        digests=tuple(digests),
        fitness=np.stack(fitness),
        components=np.stack(components),
        descriptors=np.stack(descriptors),
    )


def _span(manager: RunManager, worker: str) -> tuple[Job, RunLoop]:
    job = _lease(manager, worker)
    assert job.span > 1 and job.state is not None and (job.start, job.stop) == (0, 6)
    loop = RunLoop(job.config, GAState.from_arrays(job.state))
    assert loop.generation == job.key.generation
    assert loop.ask().tobytes() == job.genomes.tobytes()
    return job, loop


def test_a_span_moves_its_lease_on_each_generation_until_used_up(
    make_manager: Callable[..., RunManager],
) -> None:
    manager = make_manager(**SPANS)
    manager.scheduler.join("w", speed=FAST)
    run_id = manager.create_run(SPANNED)
    job, loop = _span(manager, "w")
    assert (job.key.generation, job.span) == (0, 3)
    for g in range(3):  # one generation a result
        assert manager.scheduler.settle(_span_result(loop, job.key, "w")).accepted
        held = {"pending": 0, "leased": 1, "done": 0}
        assert manager.scheduler.counts() == (
            held if g < 2 else {**held, "pending": 1, "leased": 0}
        )
    manager.flush()
    assert _run_row(manager, run_id) == ("running", 3)
    job, loop = _span(manager, "w")
    assert (job.key.generation, job.span) == (3, 3)  # capped at the run's end
    assert manager.scheduler.settle(_span_result(loop, job.key, "w", k=2)).accepted  # two at once
    assert manager.scheduler.settle(_span_result(loop, job.key, "w")).accepted
    drain(manager)  # its champion's stages
    assert _run_row(manager, run_id) == ("completed", 6)
    assert manager.best(run_id).sha256 == evolve(SPANNED).best.sha256


def test_a_span_s_generation_of_other_genomes_is_an_error_and_ends_its_worker_s_spans(
    make_manager: Callable[..., RunManager],
) -> None:
    manager = make_manager(**SPANS)
    manager.scheduler.join("w", speed=FAST)
    run_id = manager.create_run(SPANNED)
    job, loop = _span(manager, "w")
    assert manager.scheduler.settle(_span_result(loop, job.key, "w")).accepted
    other = RunLoop(SPANNED.model_copy(update={"seed": 4}))  # another GA: other genomes
    other.tell(*evaluate_population(SPANNED, other.generation, other.ask()))
    wrong = _span_result(other, job.key, "w")
    assert wrong.key.generation == 1
    ack = manager.scheduler.settle(wrong)
    assert (ack.accepted, ack.reason) == (True, "error recorded")
    assert manager.scheduler.counts() == {"pending": 1, "leased": 0, "done": 0}
    retry = _lease(manager, "w")
    assert (retry.key.generation, retry.span, retry.state) == (1, 1, None)  # no more spans
    assert manager.scheduler.settle(run_job(retry, "w")).accepted
    drain(manager, "w")
    assert _run_row(manager, run_id) == ("completed", 6)
    assert manager.best(run_id).sha256 == evolve(SPANNED).best.sha256


def test_a_span_s_generation_without_its_digest_is_an_error(
    make_manager: Callable[..., RunManager],
) -> None:
    manager = make_manager(**SPANS)
    manager.scheduler.join("w", speed=FAST)
    manager.create_run(SPANNED)
    job, loop = _span(manager, "w")
    first = _span_result(loop, job.key, "w")
    assert manager.scheduler.settle(first.model_copy(update={"digests": ()})).accepted  # asked here
    bare = _span_result(loop, job.key, "w").model_copy(update={"digests": ()})
    ack = manager.scheduler.settle(bare)
    assert (ack.accepted, ack.reason) == (True, "error recorded")
    assert manager.scheduler.counts() == {"pending": 1, "leased": 0, "done": 0}


def test_a_span_is_only_for_a_whole_generation_and_never_passes_the_run(
    make_manager: Callable[..., RunManager],
) -> None:
    manager = make_manager(**SPANS)
    manager.create_run(SPANNED)  # no worker known: cut by job_size
    manager.scheduler.join("w", speed=FAST)
    job = _lease(manager, "w")
    assert ((job.start, job.stop), job.span, job.state) == ((0, 2), 1, None)
    short = SPANNED.model_copy(update={"generations": 2, "seed": 9})
    run_id = manager.create_run(short)  # cut whole: its only live worker spans
    while (job := _lease(manager, "w")).key.run_id != run_id:
        pass
    assert ((job.start, job.stop), job.span) == ((0, 6), 2)  # 3 wanted, 2 left


@pytest.mark.parametrize("how", ["leave", "expire", "pause", "cut"])
def test_a_span_ends_when_its_lease_returns_its_run_pauses_or_the_cut_changes(
    make_manager: Callable[..., RunManager], how: str
) -> None:
    """Leave, expiry: its generation returns, the worker's result is dropped (a lapsed
    generation, never leased to its credential again, goes to the server's referee: no other
    worker is live). Pause: the result in hand counts, the next generation waits. A worker
    joining mid-span: the next generation is cut for both, so the span ends there and its
    result is dropped."""
    manager = make_manager(**SPANS)
    manager.scheduler.join("w", speed=FAST)
    run_id = manager.create_run(SPANNED)
    job, loop = _span(manager, "w")
    if how == "leave":
        assert manager.scheduler.leave("w") == [job.key]
    elif how == "expire":
        deadline = manager.scheduler.next_deadline()
        assert deadline is not None
        assert eventually(lambda: manager.scheduler.now() >= deadline, timeout=10.0)
        assert manager.scheduler.expire() == 1
    elif how == "pause":
        manager.pause(run_id)
    else:
        manager.scheduler.join("x")  # its speed unknown: no longer a span's whole generation
    ack = manager.scheduler.settle(_span_result(loop, job.key, "w"))
    if how == "leave":
        assert ack.accepted is False
        assert manager.scheduler.counts() == {"pending": 1, "leased": 0, "done": 0}
        return
    if how == "expire":
        assert ack.accepted is False
        assert eventually(lambda: manager.scheduler.totals()["done"] == 1, timeout=60.0)
        return
    assert ack.accepted is True
    pending = 2 if how == "cut" else 1
    assert manager.scheduler.counts() == {"pending": pending, "leased": 0, "done": 0}
    assert manager.scheduler.settle(_span_result(loop, job.key, "w")).accepted is False
    manager.flush()
    assert _run_row(manager, run_id) == ("paused" if how == "pause" else "running", 1)


# any order of worker events and restarts --------------------------------------------------------

EVENTS = st.lists(
    st.tuples(
        st.sampled_from(["lease", "settle", "leave", "fast", "flush", "restart"]),
        st.integers(0, 2**16),
    ),
    max_size=25,
)


@dataclasses.dataclass
class _Held:
    """A result a worker holds, and for a span its loop and the generations left after it."""

    result: Result
    loop: RunLoop | None = None
    left: int = 0


def _work(job: Job, worker: str) -> _Held:
    """What a worker does with a job: evaluate it, or evolve a span's first generation."""
    if job.state is None:
        return _Held(run_job(job, worker))
    loop = RunLoop(job.config, GAState.from_arrays(job.state))
    return _Held(_span_result(loop, job.key, worker), loop, job.span - 1)


def _settle(manager: RunManager, held: _Held) -> tuple[bool, _Held | None]:
    """Settle a held result: whether it was accepted, and a span's next generation (the
    worker goes on with its span; the result is dropped if the lease did not move on)."""
    accepted = manager.scheduler.settle(held.result).accepted
    if not (accepted and held.loop is not None and held.left > 0):
        return accepted, None
    following = _span_result(held.loop, held.result.key, held.result.worker)
    return accepted, _Held(following, held.loop, held.left - 1)


@pytest.fixture(scope="module")
def tiny_best() -> str:
    return evolve(TINY).best.sha256


@settings(max_examples=15, deadline=None)
@given(events=EVENTS)
def test_any_order_of_worker_events_and_restarts_gives_the_local_result(
    tmp_path_factory: pytest.TempPathFactory,
    tiny_best: str,
    events: list[tuple[str, int]],
) -> None:
    """Leases (asking again drops what a worker held), results (also from before a restart,
    and a span's generations), departures, fast workers (their whole generations go in spans),
    writes (a restart loses the unwritten ones, as a crash would) and server restarts: the
    run ends with `evolve`'s best controller, no generation is committed twice, and each genome
    is stored once."""
    engine = make_engine(f"sqlite:///{tmp_path_factory.mktemp('q') / 'colony.db'}")
    upgrade(engine)
    settings_ = Settings(**{**BASE, "span_below_seconds": 0.1})
    manager = RunManager(engine, settings_)
    run_id = manager.create_run(TINY)
    held: list[_Held] = []
    for kind, n in events:
        worker = f"w{n % 3}"
        if kind == "lease" and (job := manager.scheduler.lease(worker)) is not None:
            held.append(_work(job, worker))
        elif kind == "settle" and held:
            following = _settle(manager, held.pop(n % len(held)))[1]
            if following is not None:
                held.append(following)
        elif kind == "leave":
            manager.scheduler.leave(worker)
        elif kind == "fast":
            manager.scheduler.join(worker, speed=1e6)
        elif kind == "flush":
            manager.flush()
        elif kind == "restart":  # the old process dies; its workers' results may still arrive
            manager = RunManager(engine, settings_)
            manager.recover()
    while held:
        following = _settle(manager, held.pop(0))[1]
        if following is not None:
            held.append(following)
    for name in ("w0", "w1", "w2"):
        manager.scheduler.leave(name)
    while (job := manager.scheduler.lease("drain")) is not None:
        item: _Held | None = _work(job, "drain")
        while item is not None:
            accepted, item = _settle(manager, item)
            assert accepted
        manager.flush()
    manager.flush()
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation) == ("completed", 3)
        assert [g.generation for g in crud.list_generations(session, run_id=run_id)] == [0, 1, 2]
    assert manager.best(run_id).sha256 == tiny_best
    _assert_rebuilt(engine, run_id, TINY, _local_ranked(TINY), {TINY.generations - 1})
    engine.dispose()


# checkpoints: genomes every few generations, the others replayed ------------------------------

COPIES = RunConfig(population=12, generations=6, steps=10, trials=2, job_size=5, seed=5)
LITERAL = COPIES.model_copy(update={"ga": GAConfig(selection="literal"), "seed": 6})


def _local_ranked(config: RunConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every generation's genomes and components in rank order, composed as `evolve`
    composes the GA."""
    lay, params = layout(config.network_spec), GAParams.from_config(config)
    state, out = init(lay, params), []
    for g in range(config.generations):
        genomes, state = ask(ga_rng(config.seed, g), state, params, lay)
        fitness, components, _ = evaluate_population(config, g, genomes)
        state, metrics = tell(genomes, fitness, state, params)
        assert state.ranked is not None
        out.append((state.ranked, components[metrics.order]))
    assert out[-1][0].tobytes() == np.asarray(evolve(config).state.ranked).tobytes()
    return out


def _drive(manager: RunManager, *, until: int | None = None) -> None:
    """Evaluate and settle jobs (written every other result, so flushes write one generation
    or several) until the run ends, or until generation `until` is leased with every earlier
    one written."""
    settled = 0
    while (result := evaluated(manager, "w")) is not None:
        if until is not None and result.key.generation >= until:
            break
        assert manager.scheduler.settle(result).accepted
        settled += 1
        if settled % 2:
            manager.flush()
    manager.flush()


def _assert_rebuilt(
    engine: sa.Engine,
    run_id: int,
    config: RunConfig,
    expected: list[tuple[np.ndarray, np.ndarray]],
    checkpoints: set[int],
) -> None:
    """Genomes, components and GA state only at `checkpoints`; every generation reads back
    exactly `evolve`'s genomes and components, replayed or not."""
    m = config.replacement_count
    with Session(engine) as session:
        stored = crud.stored(session, run_id=run_id, generations=range(len(expected)))
        assert sorted(stored) == list(range(len(expected)))
        assert {g for g, told in stored.items() if told.checkpoint} == checkpoints
        states = session.scalars(
            sa.select(Generation.generation).where(
                Generation.run_id == run_id, Generation.state.is_not(None)
            )
        )
        assert set(states) == checkpoints
        for g, (ranked, components) in enumerate(expected):
            found, genomes = crud.ranked(session, run_id=run_id, generation=g, components=True)
            assert genomes.tobytes() == ranked.tobytes(), g
            assert found.components is not None
            assert found.components.tobytes() == components.tobytes(), g
            one = crud.ranked(session, run_id=run_id, generation=g, rank=m)[1]
            assert one.tobytes() == ranked[m : m + 1].tobytes()
        for rank in (0, m, 2 * m, config.population - 1):  # elite, mutant, fill, k-2 elite
            document = ranked_document(session, run_id, rank)
            assert document.weights.tobytes() == expected[-1][0][rank].tobytes()


@pytest.mark.parametrize(
    ("config", "every"), [(COPIES, 2), (COPIES, 50), (LITERAL, 1)], ids=["2", "50", "literal-1"]
)
def test_a_run_stores_genomes_at_checkpoints_and_rebuilds_evolve_bit_for_bit(
    tmp_path: Path, config: RunConfig, every: int
) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    manager = RunManager(engine, Settings(**{**BASE, "checkpoint_every": every}))
    run_id = manager.create_run(config)
    _drive(manager)
    last = config.generations - 1
    checkpoints = {g for g in range(config.generations) if (g + 1) % every == 0} | {last}
    _assert_rebuilt(engine, run_id, config, _local_ranked(config), checkpoints)
    assert manager.best(run_id).sha256 == evolve(config).best.sha256
    engine.dispose()


@pytest.mark.parametrize("restart_after", [1, 2, 4])
def test_a_restart_between_checkpoints_replays_and_goes_on_as_evolve(
    tmp_path: Path, restart_after: int
) -> None:
    """A restarted manager rebuilds the run's loop from the checkpoint before its last written
    generation (or from its seed before the first), told the stored fitness since."""
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    settings_ = Settings(**{**BASE, "checkpoint_every": 2})
    first = RunManager(engine, settings_)
    run_id = first.create_run(COPIES)
    _drive(first, until=restart_after)
    second = RunManager(engine, settings_)
    second.recover()
    _drive(second)
    with second.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and run.status == "completed"
    _assert_rebuilt(engine, run_id, COPIES, _local_ranked(COPIES), {1, 3, 5})
    assert second.best(run_id).sha256 == evolve(COPIES).best.sha256
    engine.dispose()


def test_a_store_of_every_population_migrates_to_checkpoints(tmp_path: Path) -> None:
    """A database written before checkpoints (every generation's individuals by rank, a copy
    pointing to the row with its bytes) upgrades in place: the last generation keeps its
    genomes, the others are replayed, and every one reads back as before."""
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    command.upgrade(alembic_config(engine), "0007_served_checksums")
    expected = _local_ranked(COPIES)
    loop = RunLoop(COPIES)
    held: dict[bytes, tuple[int, int]] = {}  # the previous generation's genomes: where they are
    with engine.begin() as conn:
        conn.execute(
            sa.text(
                "INSERT INTO runs (id, config, seed, status, generation, evaluations, tags, "
                "created_at) VALUES (1, :config, 5, 'completed', 6, 72, '[]', '2026-01-01')"
            ),
            {"config": COPIES.model_dump_json()},
        )
        for g, (ranked, components) in enumerate(expected):
            fitness, _, descriptors = evaluate_population(COPIES, g, loop.ask())
            told = loop.tell(fitness, None, descriptors)
            order, own = told.metrics.order, list[np.ndarray]()
            genome_at = np.zeros((len(order), 2), dtype=np.int32)
            for r, genome in enumerate(ranked):
                if genome.tobytes() in held:  # a copy: no bytes of its own
                    genome_at[r] = held[genome.tobytes()]
                else:
                    genome_at[r] = (g, len(own))
                    own.append(genome)
            assert g == 0 or len(own) < len(order)  # some copies point back
            held = {
                genome.tobytes(): (int(a), int(b))
                for genome, (a, b) in zip(ranked, genome_at, strict=True)
            }
            frame = encode_frame(
                {"kind": "population"},
                {
                    "index": order.astype(np.int32),
                    "parent": np.full(len(order), -1, dtype=np.int32),
                    "fitness": told.fitness[order],
                    "components": components,
                    "descriptors": np.asarray(told.descriptors)[order],
                    "genome_at": genome_at,
                    "genomes": np.array(own),
                },
            )
            conn.execute(
                sa.insert(Generation).values(
                    run_id=1,
                    generation=g,
                    best=0.0,
                    mean=0.0,
                    worst=0.0,
                    nan_count=0,
                    state=encode_frame({"kind": "ga-state"}, told.after.to_arrays(ranked=False)),
                    population=frame,
                )
            )
    upgrade(engine)
    _assert_rebuilt(engine, 1, COPIES, expected, {COPIES.generations - 1})
    engine.dispose()


def test_a_run_failed_while_the_store_refuses_writes_is_recorded_failed_once_it_accepts(
    tmp_path: Path,
) -> None:
    """The server's own evaluation failed a run while every write was refused: the failure
    is written once the store accepts writes again, not dropped (the run would stay
    `running` in the store, holding a slot, with no jobs)."""
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    manager = RunManager(engine, Settings(**BASE))
    run_id = manager.create_run(TINY)
    job = manager.scheduler.lease("w")
    assert job is not None
    refused = {"on": True}

    @sa.event.listens_for(engine, "begin")
    def read_only(conn: sa.Connection) -> None:
        conn.exec_driver_sql(f"PRAGMA query_only={'ON' if refused['on'] else 'OFF'}")

    failing = Result(key=job.key, worker="w", start=job.start, stop=job.stop, error="x")
    manager.scheduler.join("w", listed=False)  # an in-process executor: its error fails the run
    manager.scheduler.settle(failing)
    with pytest.raises(sa.exc.OperationalError):
        manager.flush()
    refused["on"] = False
    manager.flush()
    assert _run_row(manager, run_id)[0] == "failed"
    engine.dispose()


def test_a_stored_config_todays_validators_refuse_fails_its_run_not_the_servers_start(
    tmp_path: Path,
) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    run_id = RunManager(engine, Settings(**BASE)).create_run(TINY)
    with engine.begin() as conn:  # as an older release might have stored it
        conn.execute(
            sa.text("UPDATE runs SET config = :c, status = 'running' WHERE id = :i"),
            {"c": TINY.model_copy(update={"population": 3}).model_dump_json(), "i": run_id},
        )
    restarted = RunManager(engine, Settings(**BASE))
    restarted.recover()  # raised pydantic's ValidationError: the server did not start
    with restarted.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and run.status == "failed"
        assert "cannot resume" in (run.error or "")
    engine.dispose()
