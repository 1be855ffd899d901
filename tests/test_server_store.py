"""The store: migrations, population frames, GA state round trip, the job queue's contract,
and genomes stored once per run (Eq 11's copies point to the generation holding their bytes)."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa
from alembic.script import ScriptDirectory
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from sqlalchemy.orm import Session

from evorobotics.evaluate import evaluate
from evorobotics.evolution import evaluate_population, evolve
from evorobotics.ga import GAParams, ask, ga_rng, init, tell
from evorobotics.layout import layout
from schemas.run import GAConfig, RunConfig
from schemas.wire import decode_frame, encode_frame
from server import crud
from server.db import Checkpointer, alembic_config, make_engine, upgrade
from server.dispatch import WRITE_AFTER_S, QueueSource
from server.errors import NotFoundError, ServerError
from server.jobs import JobKey, JobResult
from server.manager import (
    RunManager,
    _lineage,
    _Origins,
    decode_state,
    encode_state,
    stored_ranked,
)
from server.models import Generation
from server.population import Population, PopulationError, decode, encode, resolve
from server.robots import ranked_document
from server.settings import Settings
from tests.helpers import eventually

TABLES = {"runs", "generations", "controllers", "robots"}
SMALL = RunConfig(population=12, generations=3, steps=10, trials=2, job_size=5)


@pytest.fixture
def manager(tmp_path: Path) -> Iterator[RunManager]:
    """A manager on a fresh SQLite file, without executors: tests drive the queue by hand."""
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    yield RunManager(engine, Settings(db_url="unused", lease_seconds=10.0, max_attempts=2))
    engine.dispose()


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
    data=st.data(),
)
def test_a_population_frame_round_trips_bits_and_resolves_copies(
    n: int, trials: int, width: int, data: st.DataObject
) -> None:
    """Any mix of own genomes and copies of an earlier generation's rows reads back bit for
    bit: NaN fitness (a failed evaluation), NaN payloads and -0.0 in genomes included."""
    own = data.draw(st.lists(st.booleans(), min_size=n, max_size=n))
    earlier = data.draw(hnp.arrays(np.float64, (3, width), elements=st.floats(width=64)))
    genomes = data.draw(hnp.arrays(np.float64, (sum(own), width), elements=st.floats(width=64)))
    rows = iter(range(sum(own)))
    genome_at = np.array(
        [(5, next(rows)) if mine else (2, data.draw(st.integers(0, 2))) for mine in own],
        dtype=np.int64,
    ).reshape(n, 2)
    stored = Population(
        index=np.array(data.draw(st.permutations(range(n))), dtype=np.int64),
        parent=np.array(data.draw(st.lists(st.integers(-1, 99), min_size=n, max_size=n))),
        fitness=data.draw(hnp.arrays(np.float64, n, elements=st.floats(width=64))),
        components=data.draw(hnp.arrays(np.float64, (n, trials, 4), elements=st.floats())),
        genome_at=genome_at,
        genomes=genomes,
    )
    back = decode(encode(stored))
    for name in ("index", "parent", "fitness", "components", "genome_at", "genomes"):
        assert (
            getattr(back, name).tobytes()
            == getattr(stored, name).astype(getattr(back, name).dtype).tobytes()
        ), name
    holders = {2: dataclasses.replace(stored, genomes=earlier)}
    asked: list[list[int]] = []

    def load(gs: Iterable[int]) -> dict[int, Population]:
        asked.append(list(gs))
        return {g: holders[g] for g in gs if g in holders}

    resolved = resolve(5, back, load)
    for rank, (g, row) in enumerate(genome_at.tolist()):
        source = genomes if g == 5 else earlier
        assert resolved[rank].tobytes() == source[row].tobytes()
    if n and not all(own):
        with pytest.raises(PopulationError, match="not stored"):
            resolve(5, back, lambda gs: {})
    some = data.draw(st.lists(st.integers(0, max(n - 1, 0)), max_size=n))
    asked.clear()
    assert resolve(5, back, load, some).tobytes() == resolved[some].tobytes()
    assert asked == ([[2]] if any(not own[r] for r in some) else [])  # only what they need


def test_a_frame_of_another_kind_shape_or_dtype_is_refused() -> None:
    with pytest.raises(PopulationError, match="kind"):
        decode(encode_state(init(layout(SMALL.network_spec), GAParams.from_config(SMALL))))
    with pytest.raises(PopulationError, match="not a frame"):
        decode(b"EVC1 garbage")
    good = Population(
        index=np.arange(3),
        parent=np.arange(3),
        fitness=np.zeros(3),
        components=np.zeros((3, 1, 4)),
        genome_at=np.zeros((3, 2), dtype=np.int64),
        genomes=np.zeros((1, 2)),
    )
    assert len(decode(encode(good))) == 3
    for name, value in [
        ("parent", np.arange(2)),
        ("components", np.zeros((3, 4))),
        ("genome_at", np.zeros(3, dtype=np.int64)),
        ("genomes", np.zeros(2)),
    ]:
        with pytest.raises(PopulationError, match="shapes"):
            decode(encode(dataclasses.replace(good, **{name: value})))
    arrays = {name: getattr(good, name) for name in ("index", "parent", "fitness", "components")}
    floats = encode_frame(  # `encode` casts: a frame written otherwise
        {"kind": "population"}, {**arrays, "genome_at": np.zeros((3, 2)), "genomes": good.genomes}
    )
    with pytest.raises(PopulationError, match="'genome_at' is not of kind 'i'"):
        decode(floats)
    narrow = dataclasses.replace(good, genome_at=np.array([[1, 0], [1, 0], [0, 0]]))
    with pytest.raises(PopulationError, match="2 x float64, generation 0's 3 x float64"):
        resolve(1, narrow, lambda gs: {0: dataclasses.replace(good, genomes=np.zeros((1, 3)))})


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
@given(st.integers(0, 2**32), st.integers(0, 3))
def test_ga_state_round_trips_through_the_store_encoding(seed: int, generations: int) -> None:
    config = SMALL.model_copy(update={"seed": seed})
    lay, params = layout(config.network_spec), GAParams.from_config(config)
    state = init(lay, params)
    for g in range(generations):
        genomes, state = ask(ga_rng(seed, g), state, params, lay)
        fitness = np.random.default_rng(g).normal(size=config.population)
        state, _ = tell(genomes, fitness, state, params)
    back = decode_state(encode_state(state))
    for name, value in state.to_arrays().items():
        assert np.array_equal(back.to_arrays()[name], value)
    a, _ = ask(ga_rng(seed, generations), state, params, lay)
    b, _ = ask(ga_rng(seed, generations), back, params, lay)
    assert a.tobytes() == b.tobytes()


def _evaluate(manager: RunManager, worker: str, now: float) -> tuple[JobKey, JobResult] | None:
    job = manager.queue.lease(worker, now)
    if job is None:
        return None
    ev = evaluate(job.config, job.key.generation, job.genomes)
    return job.key, JobResult(ev.fitness, ev.components)


def _first_generation_written(manager: RunManager) -> int:
    """A SMALL run with its generation 0 evaluated (its 3 jobs) and written; its id."""
    run_id = manager.create_run(SMALL)
    for _ in range(3):
        done = _evaluate(manager, "w", 0.0)
        assert done is not None
        manager.queue.complete(*done)
    return run_id


def test_a_job_sizer_cuts_later_generations_and_the_run_matches_evolve(
    manager: RunManager,
) -> None:
    """Generation 0 is cut by the run's job_size; from the sizer on, by the sizer (the zenoh
    dispatcher's one job per worker); fitness does not depend on the cut."""
    run_id = manager.create_run(SMALL)
    cuts: list[list[tuple[int, int]]] = []
    for g in range(SMALL.generations):
        jobs = []
        while (job := manager.queue.lease("w", 0.0)) is not None:
            jobs.append(job)
        cuts.append([(j.start, j.stop) for j in jobs])
        if g == 0:  # generation 0 is cut already; its last result cuts generation 1
            manager.queue.set_job_sizer(lambda config, _generation: config.population)
        for job in jobs:
            ev = evaluate(job.config, job.key.generation, job.genomes)
            manager.queue.complete(job.key, JobResult(ev.fitness, ev.components))
    assert cuts == [[(0, 5), (5, 10), (10, 12)], [(0, 12)], [(0, 12)]]
    assert manager.best(run_id) == evolve(SMALL).best.sha256


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


def test_jobs_are_fixed_slices_and_a_duplicate_result_counts_once(manager: RunManager) -> None:
    run_id = manager.create_run(SMALL)
    leased = [manager.queue.lease("w", 0.0) for _ in range(3)]
    assert [(j.start, j.stop) for j in leased if j] == [(0, 5), (5, 10), (10, 12)]
    assert manager.queue.lease("w", 0.0) is None
    results = []
    for job in leased:
        assert job is not None
        ev = evaluate(job.config, job.key.generation, job.genomes)
        results.append((job.key, JobResult(ev.fitness, ev.components)))
    assert manager.queue.complete(*results[0]) is True
    assert manager.queue.complete(*results[0]) is False  # duplicate: acknowledged, dropped
    for key, result in results[1:]:
        assert manager.queue.complete(key, result) is True
    assert manager.queue.complete(*results[2]) is False  # late: generation already committed
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None
        assert (run.generation, run.evaluations) == (1, SMALL.population)
        ranked = crud.ranked(session, run_id=run_id, generation=0)[0]
    assert sorted(ranked.index.tolist()) == list(range(SMALL.population))
    values = ranked.fitness.tolist()
    assert np.isfinite(values).all() and values == sorted(values, reverse=True)


def test_result_of_wrong_shape_is_refused(manager: RunManager) -> None:
    manager.create_run(SMALL)
    job = manager.queue.lease("w", 0.0)
    assert job is not None
    with pytest.raises(ValueError, match="shapes"):
        manager.queue.complete(job.key, JobResult(np.zeros(2), np.zeros((2, 2, 4))))


def test_expired_lease_goes_back_and_late_result_is_still_counted_once(
    manager: RunManager,
) -> None:
    manager.create_run(SMALL.model_copy(update={"job_size": 12}))
    first = _evaluate(manager, "slow", now=0.0)
    assert first is not None and manager.queue.lease("other", 1.0) is None
    assert manager.queue.expire(now=5.0) == 0  # deadline 10 not yet passed
    assert manager.queue.expire(now=11.0) == 1
    second = _evaluate(manager, "fast", now=11.0)
    assert second is not None and second[0] == first[0]
    assert manager.queue.complete(*first) is True  # the slow worker's late result is valid
    assert manager.queue.complete(*second) is False


def test_runs_share_the_workers_fairly(manager: RunManager) -> None:
    a = manager.create_run(SMALL.model_copy(update={"job_size": 3}))
    b = manager.create_run(SMALL.model_copy(update={"job_size": 3, "seed": 1}))
    order = []
    for _ in range(6):
        job = manager.queue.lease("w", 0.0)
        assert job is not None
        order.append(job.key.run_id)
    assert order == [a, b, a, b, a, b]


def test_paused_runs_get_no_jobs_and_failures_fail_the_run(manager: RunManager) -> None:
    run_id = manager.create_run(SMALL)
    manager.pause(run_id)
    assert manager.queue.lease("w", 0.0) is None
    manager.resume(run_id)
    for attempt in range(2):
        job = manager.queue.lease("w", float(attempt))
        assert job is not None and job.key.index == 0
        assert manager.queue.fail(job.key, "boom") is True
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and run.status == "failed" and "boom" in (run.error or "")
        assert crud.job_counts(session) == {"pending": 0, "leased": 0, "done": 0}


def test_generations_commit_whole_under_concurrent_completion(manager: RunManager) -> None:
    """Two threads complete jobs at once; every committed generation is complete."""
    run_id = manager.create_run(SMALL.model_copy(update={"job_size": 2}))
    errors: list[BaseException] = []

    def work(name: str) -> None:
        try:
            while (item := _evaluate(manager, name, 0.0)) is not None:
                manager.queue.complete(*item)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(f"t{i}",)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and run.status == "completed"
        for g in range(SMALL.generations):
            assert len(crud.ranked(session, run_id=run_id, generation=g)[0]) == 12


def test_release_returns_a_lease_at_once_and_counts_follow_the_jobs(manager: RunManager) -> None:
    manager.create_run(SMALL)
    first = manager.queue.lease("gone", 0.0)
    second = _evaluate(manager, "w", 0.0)
    assert first is not None and second is not None
    with manager.sessions() as session:
        assert crud.job_counts(session) == {"pending": 1, "leased": 2, "done": 0}
    assert manager.queue.complete(*second) is True
    assert manager.queue.release(second[0]) is False  # done: nothing to release
    assert manager.queue.release(first.key) is True
    assert manager.queue.release(first.key) is False  # already pending
    with manager.sessions() as session:
        assert crud.job_counts(session) == {"pending": 2, "leased": 0, "done": 1}
    again = manager.queue.lease("w", 0.0)
    assert again is not None and again.key == first.key and again.attempt == 2


def test_a_paused_run_commits_what_is_in_hand_but_leases_nothing_new(manager: RunManager) -> None:
    run_id = manager.create_run(SMALL.model_copy(update={"job_size": 12}))
    item = _evaluate(manager, "w", 0.0)
    assert item is not None
    manager.pause(run_id)
    assert manager.queue.complete(*item) is True
    assert manager.queue.lease("w", 0.0) is None
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation) == ("paused", 1)
    manager.resume(run_id)
    job = manager.queue.lease("w", 0.0)
    assert job is not None and job.key.generation == 1


def test_results_after_cancel_are_dropped(manager: RunManager) -> None:
    run_id = manager.create_run(SMALL)
    item = _evaluate(manager, "w", 0.0)
    assert item is not None
    manager.cancel(run_id)
    assert manager.queue.complete(*item) is False
    assert manager.queue.lease("w", 0.0) is None
    with manager.sessions() as session:
        assert crud.job_counts(session) == {"pending": 0, "leased": 0, "done": 0}


def test_stored_state_leaves_out_the_population_and_resume_reads_it_back(
    manager: RunManager,
) -> None:
    run_id = _first_generation_written(manager)
    with manager.sessions() as session:
        stored = crud.get_generation(session, run_id=run_id, generation=0)
        assert stored is not None
        arrays = decode_frame(stored.state)[1]
        assert "ranked" not in arrays and "ranked_fitness" in arrays
        ranked = stored_ranked(session, run_id=run_id, generation=0)
    params = GAParams.from_config(SMALL)
    lay = layout(SMALL.network_spec)
    genomes, _ = ask(ga_rng(SMALL.seed, 0), init(lay, params), params, lay)
    fitness = np.concatenate(
        [evaluate(SMALL, 0, genomes[a:b]).fitness for a, b in ((0, 5), (5, 10), (10, 12))]
    )
    expected, _ = tell(genomes, fitness, init(lay, params), params)
    assert expected.ranked is not None and ranked.tobytes() == expected.ranked.tobytes()


def test_deferred_write_installs_the_next_generation_first(manager: RunManager) -> None:
    """`complete(defer=True)` hands out generation 1 before generation 0 is written; the
    write happens at `flush` (or before any later completion), exactly once, not at the
    housekeeper's tick (which retries only refused writes: it would break the batches)."""
    run_id = manager.create_run(SMALL)
    items = [_evaluate(manager, "w", 0.0) for _ in range(3)]
    for item in items[:-1]:
        assert item is not None and manager.queue.complete(*item, defer=True) is True
    assert items[-1] is not None and manager.queue.complete(*items[-1], defer=True) is True
    assert manager.queue.unwritten() == 1
    following = manager.queue.lease("w", 0.0)
    assert following is not None and following.key.generation == 1
    manager.settle_write_failures()  # the housekeeper: no write refused, so it waits too
    assert manager.queue.unwritten() == 1
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and run.generation == 0
        assert crud.get_generation(session, run_id=run_id, generation=0) is None
    manager.queue.flush()
    manager.queue.flush()
    assert manager.queue.unwritten() == 0
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.generation, run.evaluations) == (1, SMALL.population)
        assert len(crud.ranked(session, run_id=run_id, generation=0)[0]) == 12


def test_the_dispatcher_source_writes_told_generations_together(manager: RunManager) -> None:
    """`QueueSource.flush` puts a told generation's write off until the oldest has waited
    `WRITE_AFTER_S` (one transaction for all), but writes a run's last generation at once;
    `RunManager.stop` writes whatever is left."""
    clock = [10.0]
    source = QueueSource(manager.queue, clock=lambda: clock[0])
    whole = SMALL.model_copy(update={"job_size": SMALL.population, "generations": 4})
    run_id = manager.create_run(whole)

    def tell_one() -> None:
        done = _evaluate(manager, "w", 0.0)
        assert done is not None
        assert manager.queue.complete(*done, defer=True) is True

    def written() -> int:
        with manager.sessions() as session:
            run = crud.get_run(session, run_id=run_id)
            assert run is not None
            return run.generation

    tell_one()
    assert source.flush() == pytest.approx(WRITE_AFTER_S)  # seconds to wait
    clock[0] += WRITE_AFTER_S / 2
    tell_one()
    assert source.flush() == pytest.approx(WRITE_AFTER_S / 2)  # the oldest sets the time
    assert (manager.queue.unwritten(), written()) == (2, 0)
    clock[0] = 10.0 + WRITE_AFTER_S
    assert source.flush() is None
    assert (manager.queue.unwritten(), written()) == (0, 2)
    tell_one()
    assert source.flush() is not None
    manager.stop()
    assert (manager.queue.unwritten(), written()) == (0, 3)
    tell_one()  # the last generation: written at once, the run completes
    assert source.flush() is None
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation) == ("completed", 4)


def test_cancel_writes_the_told_generation_before_cancelling(manager: RunManager) -> None:
    run_id = manager.create_run(SMALL.model_copy(update={"job_size": 12}))
    item = _evaluate(manager, "w", 0.0)
    assert item is not None and manager.queue.complete(*item, defer=True) is True
    manager.cancel(run_id)
    assert manager.queue.unwritten() == 0
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation) == ("cancelled", 1)
    assert manager.queue.lease("w", 0.0) is None


def test_listeners_hear_of_new_and_returned_jobs_until_removed(manager: RunManager) -> None:
    calls: list[int] = []
    remove = manager.queue.add_listener(lambda: calls.append(1))
    manager.create_run(SMALL)
    assert len(calls) == 1  # the run's first generation
    job = manager.queue.lease("w", 0.0)
    assert job is not None and len(calls) == 1  # leasing announces nothing
    assert manager.queue.release(job.key) is True and len(calls) == 2
    remove()
    again = manager.queue.lease("w", 0.0)
    assert again is not None and manager.queue.release(again.key) is True
    assert len(calls) == 2


TINY = RunConfig(population=6, generations=3, steps=5, trials=1, job_size=2, seed=11)
EVENTS = st.lists(
    st.tuples(
        st.sampled_from(
            ["lease", "complete", "release", "expire", "flush", "restart", "whole", "span"]
        ),
        st.integers(),
    ),
    max_size=25,
)


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
    """Leases, results (also from before a restart), releases, expiries, deferred writes (a
    restart loses the unwritten ones, as a crash would), server restarts, whole generations
    and spans (their worker evolves the next generation it is leased): the run ends with
    `evolve`'s best controller, no generation is ever committed twice, and each genome is
    stored once."""
    engine = make_engine(f"sqlite:///{tmp_path_factory.mktemp('q') / 'colony.db'}")
    upgrade(engine)
    settings_ = Settings(db_url="unused", lease_seconds=10.0, max_attempts=2)
    manager = RunManager(engine, settings_)
    run_id = manager.create_run(TINY)
    held: list[tuple[JobKey, JobResult, str]] = []
    now = 0.0
    for kind, n in events:
        now += 1.0
        worker = f"w{n % 3}"
        if kind == "lease" and (item := _evaluate(manager, worker, now)) is not None:
            held.append((*item, worker))
        elif kind == "complete" and held:
            key, result, worker = held.pop(n % len(held))
            manager.queue.complete(key, result, defer=n % 2 == 0, now=now)
            following = JobKey(key.run_id, key.generation + 1, 0)
            if manager.queue.leased_to(following) == worker:  # a span goes on
                genomes = manager.queue.genomes(following)
                assert genomes is not None
                ev = evaluate(TINY, following.generation, genomes)
                held.append((following, JobResult(ev.fitness, ev.components), worker))
        elif kind == "whole":
            manager.queue.set_job_sizer(lambda config, _generation: config.population)
        elif kind == "span" and held:
            key, _, worker = held[n % len(held)]
            manager.queue.grant_span(key, worker, n % 3 + 2)
        elif kind == "flush":
            manager.queue.flush()
        elif kind == "release" and held:
            manager.queue.release(held[n % len(held)][0])
        elif kind == "expire":
            manager.queue.expire(now + 10.0 * (n % 2))
        elif kind == "restart":  # the old process dies; its workers' results may still arrive
            manager = RunManager(engine, settings_)
            manager.recover()
    for key, result, _ in held:
        manager.queue.complete(key, result)
    while (item := _evaluate(manager, "drain", now)) is not None:
        assert manager.queue.complete(*item) is True
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and (run.status, run.generation) == ("completed", 3)
        assert [g.generation for g in crud.list_generations(session, run_id=run_id)] == [0, 1, 2]
    assert manager.best(run_id) == tiny_best
    _assert_stored_once(engine, run_id, TINY, _local_ranked(TINY))
    engine.dispose()


def test_a_failed_evaluation_is_stored_as_null_ranks_last_and_the_run_goes_on(
    manager: RunManager,
) -> None:
    run_id = manager.create_run(SMALL)
    for _ in range(3):
        done = _evaluate(manager, "w", 0.0)
        assert done is not None
        key, result = done
        if key.index == 0:  # one individual's evaluation failed
            result = JobResult(
                np.where(np.arange(5) == 2, np.nan, result.fitness), result.components
            )
        assert manager.queue.complete(key, result) is True
    with manager.sessions() as session:
        ranked = crud.ranked(session, run_id=run_id, generation=0)[0]
    assert [int(ranked.index[r]) for r in range(12) if ranked.fitness_of(r) is None] == [2]
    assert ranked.index[-1] == 2  # NaN never wins: it ranks last
    assert _evaluate(manager, "w", 0.0) is not None  # generation 1 was asked


def _whole(manager: RunManager, config: RunConfig) -> int:
    manager.queue.set_job_sizer(lambda c, _g: c.population)
    return manager.create_run(config)


def _result(config: RunConfig, generation: int, genomes: np.ndarray) -> JobResult:
    ev = evaluate(config, generation, genomes)
    return JobResult(ev.fitness, ev.components)


SPANNED = RunConfig(population=6, generations=6, steps=5, trials=1, seed=3)


def test_a_span_leases_each_next_generation_to_its_worker_until_used_up(
    manager: RunManager,
) -> None:
    run_id = _whole(manager, SPANNED)
    job = manager.queue.lease("w", 0.0)
    assert job is not None
    granted, state = manager.queue.grant_span(job.key, "w", 3)
    assert granted == 3 and state is not None and state.generation == 0
    key, genomes = job.key, job.genomes
    for g in (1, 2):  # the span's second and third generations go to "w" alone
        assert manager.queue.complete(key, _result(SPANNED, g - 1, genomes), now=float(g))
        key = JobKey(run_id, g, 0)
        assert manager.queue.leased_to(key) == "w"
        assert manager.queue.lease("x", float(g)) is None
        leased = manager.queue.genomes(key)
        assert leased is not None
        genomes = leased
    assert manager.queue.complete(key, _result(SPANNED, 2, genomes), now=3.0)
    assert manager.queue.leased_to(JobKey(run_id, 3, 0)) is None  # used up: pending again
    while (job := manager.queue.lease("x", 4.0)) is not None:
        manager.queue.complete(job.key, _result(SPANNED, job.key.generation, job.genomes))
    assert manager.best(run_id) == evolve(SPANNED).best.sha256


def test_a_span_goes_on_in_one_job_when_the_sizer_would_now_cut_slices(
    manager: RunManager,
) -> None:
    """Workers' speeds move across the span threshold mid-span: the span still gets its
    generations whole (cut, it would end and its worker's generations evaluated ahead would be
    dropped); once it is used up, the sizer cuts again."""
    run_id = _whole(manager, SPANNED)
    job = manager.queue.lease("w", 0.0)
    assert job is not None
    assert manager.queue.grant_span(job.key, "w", 3)[0] == 3
    cut_for: list[int] = []

    def slices(config: RunConfig, generation: int) -> int:
        cut_for.append(generation)
        return 2

    manager.queue.set_job_sizer(slices)
    key, genomes = job.key, job.genomes
    for g in (1, 2):
        assert manager.queue.complete(key, _result(SPANNED, g - 1, genomes), now=float(g))
        key = JobKey(run_id, g, 0)
        assert manager.queue.leased_to(key) == "w"
        leased = manager.queue.genomes(key)
        assert leased is not None and leased.shape[0] == SPANNED.population
        genomes = leased
    assert cut_for == []
    assert manager.queue.complete(key, _result(SPANNED, 2, genomes), now=3.0)
    assert cut_for == [3]
    assert manager.queue.leased_to(JobKey(run_id, 3, 0)) is None
    sliced = manager.queue.genomes(JobKey(run_id, 3, 0))
    assert sliced is not None and sliced.shape[0] == 2


def test_a_span_is_only_granted_for_a_whole_generation_to_its_holder(
    manager: RunManager,
) -> None:
    manager.create_run(SMALL)  # cut by job_size: three jobs
    job = manager.queue.lease("w", 0.0)
    assert job is not None
    assert manager.queue.grant_span(job.key, "w", 3)[0] == 1
    whole = RunConfig(population=6, generations=3, steps=5, trials=1, job_size=6)
    run_id = manager.create_run(whole)
    while (job := manager.queue.lease("w", 0.0)) is not None and job.key.run_id != run_id:
        pass
    assert job is not None
    assert manager.queue.grant_span(job.key, "other", 3)[0] == 1
    assert manager.queue.grant_span(job.key, "w", 99)[0] == whole.generations  # capped


@pytest.mark.parametrize("how", ["release", "expire", "pause"])
def test_a_span_ends_when_its_lease_returns_or_its_run_pauses(
    manager: RunManager, how: str
) -> None:
    run_id = _whole(manager, SPANNED)
    job = manager.queue.lease("w", 0.0)
    assert job is not None
    manager.queue.grant_span(job.key, "w", 5)
    if how == "release":
        manager.queue.release(job.key)
        again = manager.queue.lease("x", 1.0)
        assert again is not None and again.key == job.key
    elif how == "expire":
        assert manager.queue.expire(100.0) == 1
    else:
        manager.pause(run_id)
    manager.queue.complete(job.key, _result(SPANNED, 0, job.genomes), now=2.0)
    assert manager.queue.leased_to(JobKey(run_id, 1, 0)) is None


# genomes stored once: Eq 11's copies point to the row holding their bytes ---------------------

COPIES = RunConfig(population=12, generations=6, steps=10, trials=2, job_size=5, seed=5)
LITERAL = COPIES.model_copy(update={"ga": GAConfig(selection="literal"), "seed": 6})


def _local_ranked(config: RunConfig) -> list[np.ndarray]:
    """Every generation's genomes in rank order, composed as `evolve` composes the GA."""
    lay, params = layout(config.network_spec), GAParams.from_config(config)
    state, out = init(lay, params), []
    for g in range(config.generations):
        genomes, state = ask(ga_rng(config.seed, g), state, params, lay)
        fitness, _ = evaluate_population(config, g, genomes)
        state, _ = tell(genomes, fitness, state, params)
        assert state.ranked is not None
        out.append(state.ranked)
    assert out[-1].tobytes() == np.asarray(evolve(config).state.ranked).tobytes()
    return out


def _drive(manager: RunManager, *, until: int | None = None) -> None:
    """Evaluate and complete jobs (every other write deferred) until the run ends, or until
    generation `until` is in flight with every earlier one written."""
    while (item := _evaluate(manager, "w", 0.0)) is not None:
        if until is not None and item[0].generation >= until:
            manager.queue.release(item[0])
            break
        manager.queue.complete(*item, defer=item[0].index % 2 == 0)
    manager.queue.flush()


def _assert_stored_once(
    engine: sa.Engine, run_id: int, config: RunConfig, expected: list[np.ndarray]
) -> None:
    """Bytes only for generation 0 and the mutants of later generations; every copy points to
    bytes stored by an earlier generation, and resolves to exactly `evolve`'s genome."""
    m = config.replacement_count
    with Session(engine) as session:
        stored = crud.populations(session, run_id=run_id, generations=range(len(expected)))
        assert sorted(stored) == list(range(len(expected)))
        for g, population in stored.items():
            want = config.population if g == 0 else m
            assert len(population.genomes) == want
            at_g, at_row = population.genome_at[:, 0], population.genome_at[:, 1]
            assert (at_row[at_g == g] == np.arange(want)).all()  # own bytes, in rank order
            for holder, row in population.genome_at[at_g != g].tolist():
                assert holder < g and row < len(stored[holder].genomes)
        for g, ranked in enumerate(expected):
            population, genomes = crud.ranked(session, run_id=run_id, generation=g)
            assert genomes.tobytes() == ranked.tobytes()
            assert stored_ranked(session, run_id=run_id, generation=g).tobytes() == ranked.tobytes()
        for rank in (0, m, 2 * m, config.population - 1):  # elite, mutant, fill, k-2 elite
            document = ranked_document(session, run_id, rank)
            assert document.weights.tobytes() == expected[-1][rank].tobytes()


@pytest.mark.parametrize("config", [COPIES, LITERAL], ids=["prose", "literal"])
def test_a_run_stores_each_genome_once_and_reads_back_evolve_bit_for_bit(
    tmp_path: Path, config: RunConfig
) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    manager = RunManager(engine, Settings(db_url="unused", lease_seconds=10.0))
    run_id = manager.create_run(config)
    _drive(manager)
    _assert_stored_once(engine, run_id, config, _local_ranked(config))
    assert manager.best(run_id) == evolve(config).best.sha256
    engine.dispose()


@pytest.mark.parametrize("restart_after", [1, 2, 4])
def test_copies_after_a_restart_find_their_origins_in_the_store(
    tmp_path: Path, restart_after: int
) -> None:
    """A restarted manager has no origins in memory: its first write reads them back (one
    query) and copies still point at rows with bytes, written before the restart."""
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    settings_ = Settings(db_url="unused", lease_seconds=10.0)
    first = RunManager(engine, settings_)
    run_id = first.create_run(COPIES)
    _drive(first, until=restart_after)
    second = RunManager(engine, settings_)
    second.recover()
    _drive(second)
    with second.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and run.status == "completed"
    _assert_stored_once(engine, run_id, COPIES, _local_ranked(COPIES))
    assert second.best(run_id) == evolve(COPIES).best.sha256
    engine.dispose()


def test_a_copy_whose_bytes_differ_from_its_origin_keeps_them(manager: RunManager) -> None:
    """The lineage says which rows are copies; the bytes decide: -0.0 == 0.0 as a float, but a
    copy must give back its own bits, so it keeps them."""
    lay, params = layout(COPIES.network_spec), GAParams.from_config(COPIES)
    state = init(lay, params)
    for g in range(2):
        genomes, state = ask(ga_rng(1, g), state, params, lay)
        state, _ = tell(genomes, np.arange(12.0), state, params)
    genomes, before = ask(ga_rng(1, 2), state, params, lay)
    assert before.ranked is not None
    genomes = genomes.copy()
    genomes[0, 0], genomes[2, 0] = 0.0, -0.0  # elites: ranks 0 and 2 of the previous generation
    ranked = before.ranked.copy()
    ranked[0, 0] = ranked[2, 0] = 0.0
    before = dataclasses.replace(before, ranked=ranked)
    manager._origins[1] = _Origins(1, np.full(12, 1), np.arange(12), (0, 0))
    with manager.sessions() as session:  # the origins are in memory: no query
        at = manager._genome_at(session, 1, 2, _lineage(params, 2), genomes, before, np.arange(12))
    m = COPIES.replacement_count
    copies = [i for i in range(12) if not m <= i < 2 * m and i != 2]
    assert [i for i in range(12) if at[i, 0] != 2] == copies
    assert at[[0, 1]].tolist() == [[1, 0], [1, 1]]
    assert at[11].tolist() == [0, 0]  # the k-2 elite: rank 0 two generations back
    own = [i for i in range(12) if i not in copies]
    assert at[own].tolist() == [[2, k] for k in range(len(own))]  # stored here, in rank order
