"""The dispatcher over real zenoh on 127.0.0.1 (multicast scouting off) with an in-memory source."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from schemas.run import RunConfig
from schemas.wire import (
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    PROTOCOL,
    Idle,
    Job,
    JobKey,
    JobRequest,
    Result,
    decode_ack,
    decode_next_reply,
    decode_result_reply,
    encode_message,
    encode_result,
    encode_span_results,
    genome_digest,
    worker_key,
)
from server import crud
from server.dispatch import Dispatcher, DispatchSettings, QueueSource
from tests.helpers import eventually, free_port
from worker.main import WorkerSettings, WorkerStats, run_worker
from worker.team import Evaluator

CONFIG = RunConfig(population=12, job_size=3, generations=1, trials=2, steps=5)
W = CONFIG.network_spec.weight_count
WAIT = 20.0


def fake_fitness(genomes: np.ndarray) -> np.ndarray:
    return np.asarray(genomes.sum(axis=1), dtype=np.float64)


def fake_evaluator(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic and fast: row sums, components of the expected shape."""
    n = genomes.shape[0]
    return fake_fitness(genomes), np.full((n, config.trials, 4), float(generation))


class MemorySource:
    """A JobSource over one generation held in memory; records every call."""

    def __init__(self, config: RunConfig = CONFIG, run_id: int = 1, max_attempts: int = 2) -> None:
        self.config = config
        self.genomes = np.random.default_rng(5).normal(size=(config.population, W))
        self.pending: list[int] = []
        self.jobs: dict[int, Job] = {}
        for index, start in enumerate(range(0, config.population, config.job_size)):
            stop = min(start + config.job_size, config.population)
            key = JobKey(run_id=run_id, generation=0, index=index)
            self.jobs[index] = Job(key, start, stop, config, self.genomes[start:stop])
            self.pending.append(index)
        self.fitness: dict[int, np.ndarray] = {}
        self.leased_by: list[tuple[int, str]] = []
        self.released: list[int] = []
        self.failures: dict[int, list[str]] = {}
        self.failed_run: str | None = None
        self.max_attempts = max_attempts
        self.flushes = 0
        self.done = threading.Event()
        self.changed = threading.Condition()

    def lease(self, worker: str) -> Job | None:
        if not self.pending or self.failed_run:
            return None
        index = self.pending.pop(0)
        self.leased_by.append((index, worker))
        return self.jobs[index]

    def complete(self, result: Result) -> bool:
        index = result.key.index
        if index in self.fitness:
            return False
        assert result.fitness is not None
        self.fitness[index] = result.fitness
        if len(self.fitness) == len(self.jobs):
            self.done.set()
        self._changed()
        return True

    def fail(self, key: JobKey, error: str) -> None:
        self.failures.setdefault(key.index, []).append(error)
        if len(self.failures[key.index]) >= self.max_attempts:
            self.failed_run = error
            self.done.set()
        else:
            self.pending.insert(0, key.index)
        self._changed()

    def release(self, key: JobKey) -> None:
        self.released.append(key.index)
        self.pending.insert(0, key.index)
        self._changed()

    def flush(self) -> float | None:
        self.flushes += 1
        self._changed()
        return None

    def _changed(self) -> None:
        with self.changed:
            self.changed.notify_all()

    def wait_for(self, predicate: object, timeout: float = WAIT) -> bool:
        assert callable(predicate)
        with self.changed:
            return bool(self.changed.wait_for(predicate, timeout))

    def all_fitness(self) -> np.ndarray:
        return np.concatenate([self.fitness[i] for i in sorted(self.jobs)])


def dispatch_settings(port: int, **overrides: Any) -> DispatchSettings:
    return DispatchSettings(listen=(f"tcp/127.0.0.1:{port}",), **overrides)


def client_config(port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


@contextmanager
def worker_thread(
    port: int, name: str, evaluator: Evaluator = fake_evaluator
) -> Iterator[WorkerStats]:
    """A real worker (its own client session) in a thread; stopped and joined on exit."""
    stop = threading.Event()
    stats = WorkerStats()
    settings = WorkerSettings(
        connect=(f"tcp/127.0.0.1:{port}",), name=name, backoff_max_s=0.2, request_timeout_s=5.0
    )

    def body() -> None:
        got = run_worker(settings, stop, evaluator=evaluator)
        stats.jobs_done, stats.errors = got.jobs_done, got.errors

    thread = threading.Thread(target=body, name=f"worker-{name}")
    thread.start()
    try:
        yield stats
    finally:
        stop.set()
        thread.join(timeout=WAIT)
        assert not thread.is_alive(), f"worker {name} did not stop"


def ask(session: zenoh.Session, key: str, payload: bytes) -> zenoh.Reply:
    """Retry until the server's queryable is reachable (declarations propagate asynchronously)."""
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline:
        replies = list(session.get(key, payload=payload, timeout=5.0))
        if replies:
            return replies[0]
        threading.Event().wait(0.05)
    raise AssertionError(f"no reply on {key}")


def lease_raw(session: zenoh.Session, name: str) -> Job:
    """Lease one job as a hand-driven worker that will never finish it."""
    while True:
        reply = ask(session, KEY_JOB_NEXT, encode_message(JobRequest(worker=name)))
        assert reply.ok is not None
        job = decode_next_reply(reply.ok.payload.to_bytes())
        if isinstance(job, Job):
            return job


def test_two_workers_finish_a_generation_exactly_once() -> None:
    port = free_port()
    source = MemorySource()
    with (
        Dispatcher(dispatch_settings(port), source) as dispatcher,
        worker_thread(port, "alpha") as a,
        worker_thread(port, "beta") as b,
    ):
        assert source.done.wait(WAIT)
        assert eventually(lambda: sum(w.jobs_done for w in dispatcher.workers()) == 4)
        assert source.wait_for(lambda: source.flushes >= 1)  # deferred work once replies are out
        statuses = {w.name: w for w in dispatcher.workers()}
    assert np.array_equal(source.all_fitness(), fake_fitness(source.genomes))
    assert sorted(i for i, _ in source.leased_by) == [0, 1, 2, 3]
    assert a.jobs_done + b.jobs_done == 4
    assert dispatcher.results_accepted == 4 and dispatcher.results_dropped == 0
    assert set(statuses) == {"alpha", "beta"}
    assert all(w.state in ("idle", "busy") and w.host for w in statuses.values())
    assert all(w.robot_steps_per_s for w in statuses.values() if w.jobs_done)


class PuttingOff(MemorySource):
    """Puts its deferred work off once, by `delay` seconds; records when flush is called."""

    def __init__(self, delay: float) -> None:
        super().__init__()
        self.delay: float | None = delay
        self.calls: list[float] = []

    def flush(self) -> float | None:
        self.calls.append(time.monotonic())
        delay, self.delay = self.delay, None
        self._changed()
        return delay


def test_work_a_source_puts_off_is_done_when_it_says_with_no_message_meanwhile() -> None:
    """`flush` returns seconds on the source's own clock; the dispatcher wakes up for it."""
    source = PuttingOff(0.2)
    with Dispatcher(dispatch_settings(free_port()), source) as dispatcher:
        dispatcher.notify()  # one event, then none: only the deadline wakes it again
        assert source.wait_for(lambda: len(source.calls) >= 2)
    assert 0.2 <= source.calls[1] - source.calls[0] <= 2.0


def test_malformed_messages_are_dropped_and_serving_goes_on() -> None:
    port = free_port()
    source = MemorySource()
    with (
        Dispatcher(dispatch_settings(port), source) as dispatcher,
        zenoh.open(client_config(port)) as session,
    ):
        for key in (KEY_JOB_NEXT, KEY_JOB_RESULT):
            for junk in (b"", b"garbage", encode_message(Idle())):
                reply = ask(session, key, junk)
                assert reply.err is not None
                assert b"malformed" in reply.err.payload.to_bytes()
        token = session.liveliness().declare_token("evocolony/workers/bad name")
        with worker_thread(port, "good"):
            assert source.done.wait(WAIT)
        token.undeclare()  # type: ignore[no-untyped-call]
    assert dispatcher.malformed >= 6
    assert np.array_equal(source.all_fitness(), fake_fitness(source.genomes))


def test_vanished_worker_releases_its_job_and_its_late_result_is_dropped() -> None:
    port = free_port()
    source = MemorySource()
    with Dispatcher(dispatch_settings(port), source):
        with zenoh.open(client_config(port)) as doomed:
            token = doomed.liveliness().declare_token(worker_key("doomed"))
            job = lease_raw(doomed, "doomed")
            token.undeclare()  # type: ignore[no-untyped-call]
        assert source.wait_for(lambda: job.key.index in source.released)
        with worker_thread(port, "survivor"), zenoh.open(client_config(port)) as late:
            assert source.done.wait(WAIT)
            result = Result(
                job.key, "doomed", np.zeros(job.stop - job.start), start=job.start, stop=job.stop
            )
            ack = decode_ack(_ok(ask(late, KEY_JOB_RESULT, encode_result(result))))
        assert not ack.accepted and ack.key == job.key
    assert np.array_equal(source.all_fitness(), fake_fitness(source.genomes))


def test_a_vanished_worker_s_held_request_takes_no_job() -> None:
    """Its token gone, the request it left waiting is answered idle at once: a job leased to
    it would wait out a lease while live workers idle."""
    port = free_port()
    source = MemorySource()
    jobs = list(source.pending)
    source.pending.clear()
    settings = dispatch_settings(port, long_poll_s=30.0)
    with Dispatcher(settings, source) as dispatcher, zenoh.open(client_config(port)) as doomed:
        token = doomed.liveliness().declare_token(worker_key("doomed"))
        assert eventually(lambda: [w.name for w in dispatcher.workers()] == ["doomed"])
        request = JobRequest(worker="doomed", host="doomed-host")
        held = doomed.get(KEY_JOB_NEXT, payload=encode_message(request), timeout=WAIT)
        assert eventually(lambda: dispatcher.workers()[0].host == "doomed-host")  # held now
        token.undeclare()  # type: ignore[no-untyped-call]
        assert eventually(lambda: [w.state for w in dispatcher.workers()] == ["gone"])
        assert isinstance(decode_next_reply(_ok(next(iter(held)))), Idle)
        source.pending.extend(jobs)
        dispatcher.notify()
        with worker_thread(port, "survivor"):
            assert source.done.wait(WAIT)
    assert {worker for _, worker in source.leased_by} == {"survivor"}


def test_prefetch_is_answered_at_once_and_holding_keeps_the_prefetched_lease() -> None:
    """Protocol 3: a request naming jobs in hand is never held (idle at once when no job is
    left) and releases none of them; a result's `holding` keeps the prefetched lease."""
    port = free_port()
    source = MemorySource(CONFIG.model_copy(update={"population": 6}))
    settings = dispatch_settings(port, long_poll_s=30.0)
    with Dispatcher(settings, source), zenoh.open(client_config(port)) as session:
        first = lease_raw(session, "pre")
        prefetch = JobRequest(worker="pre", holding=(first.key,))
        second = decode_next_reply(_ok(ask(session, KEY_JOB_NEXT, encode_message(prefetch))))
        assert isinstance(second, Job) and second.key != first.key
        began = time.monotonic()
        both = JobRequest(worker="pre", holding=(first.key, second.key))
        idle = decode_next_reply(_ok(ask(session, KEY_JOB_NEXT, encode_message(both))))
        assert isinstance(idle, Idle) and time.monotonic() - began < settings.long_poll_s
        result = Result(
            first.key,
            "pre",
            fake_fitness(first.genomes),
            holding=(second.key,),
            start=first.start,
            stop=first.stop,
        )
        ack = decode_ack(_ok(ask(session, KEY_JOB_RESULT, encode_result(result))))
        assert ack.accepted and not source.released
        result = Result(
            second.key, "pre", fake_fitness(second.genomes), start=second.start, stop=second.stop
        )
        ack = decode_ack(_ok(ask(session, KEY_JOB_RESULT, encode_result(result))))
        assert ack.accepted and source.done.is_set() and not source.released


def test_a_result_for_another_cut_of_the_same_key_is_dropped_as_late() -> None:
    """Protocol 4: after a restart the same key may name another slice; a result carries its
    slice, and one that is not the lease's is late, not a failure."""
    port = free_port()
    source = MemorySource()
    with Dispatcher(dispatch_settings(port), source), zenoh.open(client_config(port)) as session:
        job = lease_raw(session, "w")
        wide = np.zeros(job.stop - job.start + 1)
        stale = Result(job.key, "w", wide, start=job.start, stop=job.stop + 1)
        ack = decode_ack(_ok(ask(session, KEY_JOB_RESULT, encode_result(stale))))
        assert not ack.accepted and not source.fitness and not source.failures
        fitness = fake_fitness(job.genomes)
        good = Result(job.key, "w", fitness, start=job.start, stop=job.stop)
        ack = decode_ack(_ok(ask(session, KEY_JOB_RESULT, encode_result(good))))
        assert ack.accepted and source.fitness[job.key.index].tobytes() == fitness.tobytes()


@pytest.mark.parametrize("more", [True, False])
def test_a_worker_prefetches_only_while_other_jobs_are_pending(more: bool) -> None:
    """Protocol 4: a job leased as the last pending one (`more` False) gets no prefetch,
    which could only come back idle."""
    port = free_port()
    source = MemorySource()
    source.jobs = {i: replace(job, more=more) for i, job in source.jobs.items()}
    with Dispatcher(dispatch_settings(port), source) as dispatcher:
        with worker_thread(port, "solo"):
            assert source.done.wait(WAIT)
        assert (dispatcher.prefetches > 0) is more
        assert (dispatcher.pipelined > 0) is more  # protocol 9: results sent ahead too
    assert np.array_equal(source.all_fitness(), fake_fitness(source.genomes))
    assert not source.released and sorted(i for i, _ in source.leased_by) == [0, 1, 2, 3]


def test_a_request_awaiting_the_reply_that_carried_a_job_keeps_its_lease() -> None:
    """Protocol 9: a worker may ask again before reading the reply to its last request; the
    job that reply carries is in flight, not lost, and the request is served as a prefetch.
    A request releases the leases it neither holds nor awaits, but for those carried by
    replies to requests the worker sent after it."""
    port = free_port()
    source = MemorySource()
    settings = dispatch_settings(port, long_poll_s=30.0)
    with Dispatcher(settings, source) as dispatcher, zenoh.open(client_config(port)) as session:

        def next_job(seq: int, awaiting: tuple[int, ...]) -> Job | Idle:
            request = JobRequest(worker="p", seq=seq, awaiting=awaiting)
            return decode_next_reply(_ok(ask(session, KEY_JOB_NEXT, encode_message(request))))

        first = next_job(1, ())
        second = next_job(2, (1,))  # not held: a prefetch
        assert isinstance(first, Job) and isinstance(second, Job) and not source.released
        fitness = fake_fitness(first.genomes)
        done = Result(first.key, "p", fitness, start=first.start, stop=first.stop)
        done = done.asking(True, (), seq=3, awaiting=(2,))
        ack, third = decode_result_reply(_ok(ask(session, KEY_JOB_RESULT, encode_result(done))))
        assert ack.accepted and isinstance(third, Job) and not source.released
        assert dispatcher.pipelined == 2
        fourth = next_job(4, (1,))  # awaits a reply already answered: the others were lost
        assert isinstance(fourth, Job)
        assert sorted(source.released) == [second.key.index, third.key.index]
        crossed = next_job(3, ())  # sent before the fourth (on the other key, say): keeps it
        assert isinstance(crossed, Job) and crossed.key != fourth.key
        assert sorted(source.released) == [second.key.index, third.key.index]


def test_a_request_awaiting_one_not_seen_yet_is_a_prefetch() -> None:
    """Protocol 9: a request that overtook one it awaits may be about to get a job through
    the other's reply: it is answered at once (never held), like a prefetch, and gets no span
    or team place."""
    port = free_port()
    source = MemorySource()
    source.pending.clear()
    settings = dispatch_settings(port, long_poll_s=30.0)
    with Dispatcher(settings, source) as dispatcher, zenoh.open(client_config(port)) as session:
        began = time.monotonic()
        request = JobRequest(worker="p", seq=10, awaiting=(9,))
        idle = decode_next_reply(_ok(ask(session, KEY_JOB_NEXT, encode_message(request))))
        assert isinstance(idle, Idle) and time.monotonic() - began < settings.long_poll_s
        assert dispatcher.pipelined == 1 and dispatcher.prefetches == 1


class LosingDispatcher(Dispatcher):
    """Loses the reply carrying its `lose`-th job sent with an Ack: the lease stands, the
    worker gets no answer (a network fault, injected where zenoh cannot be made to drop)."""

    def __init__(self, *args: Any, lose: int, **kwargs: Any) -> None:
        self.lose = lose
        self.lost_key: JobKey | None = None
        super().__init__(*args, **kwargs)

    def _send(self, query: zenoh.Query, key: str, job: Job, *args: Any, **kwargs: Any) -> None:
        if key == KEY_JOB_RESULT and job.key.index == self.lose and self.lost_key is None:
            self.lost_key = job.key
            query = _Silent()  # type: ignore[assignment]
        super()._send(query, key, job, *args, **kwargs)


class _Silent:
    def reply(self, *_args: Any, **_kwargs: Any) -> None:
        return None


def test_a_lost_reply_with_two_requests_in_flight_is_run_again_once() -> None:
    """The job a lost reply carried is released by the worker's next request for work (which
    neither holds nor awaits it) and done once; the result that reply acknowledged is
    delivered again and dropped as a duplicate."""
    port = free_port()
    source = MemorySource(CONFIG.model_copy(update={"population": 24}))
    settings = dispatch_settings(port)
    dispatcher = LosingDispatcher(settings, source, lose=3)
    with dispatcher:
        with worker_thread(port, "solo"):
            assert source.done.wait(WAIT)
        assert dispatcher.lost_key is not None and dispatcher.pipelined > 0
        assert source.released == [3] and dispatcher.results_dropped == 1
    assert sorted(i for i, _ in source.leased_by) == sorted([*range(8), 3])
    assert np.array_equal(source.all_fitness(), fake_fitness(source.genomes))


def test_expired_lease_returns_the_job_and_late_result_is_dropped() -> None:
    port = free_port()
    source = MemorySource()
    settings = dispatch_settings(port, lease_unknown_s=0.3)
    with Dispatcher(settings, source) as dispatcher, zenoh.open(client_config(port)) as hung:
        token = hung.liveliness().declare_token(worker_key("hung"))
        job = lease_raw(hung, "hung")
        assert job.lease_s == pytest.approx(0.3)
        assert source.wait_for(lambda: job.key.index in source.released)
        with worker_thread(port, "fresh"):
            assert source.done.wait(WAIT)
        result = Result(
            job.key, "hung", np.zeros(job.stop - job.start), start=job.start, stop=job.stop
        )
        ack = decode_ack(_ok(ask(hung, KEY_JOB_RESULT, encode_result(result))))
        token.undeclare()  # type: ignore[no-untyped-call]
    assert not ack.accepted
    assert dispatcher.results_dropped == 1 and dispatcher.results_accepted == 4
    assert np.array_equal(source.all_fitness(), fake_fitness(source.genomes))


def test_error_results_are_retried_then_fail_the_run() -> None:
    port = free_port()
    source = MemorySource(max_attempts=2)

    def broken(
        config: RunConfig, generation: int, genomes: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        raise RuntimeError("simulator exploded")

    with Dispatcher(dispatch_settings(port), source), worker_thread(port, "broken", broken) as st:
        assert source.done.wait(WAIT)
    assert source.failed_run is not None and "simulator exploded" in source.failed_run
    assert "broken" in source.failed_run
    assert source.failures[0] and len(source.failures[0]) == 2
    assert st.errors >= 2 and not source.fitness


def test_held_request_is_served_as_soon_as_notified() -> None:
    port = free_port()
    source = MemorySource()
    jobs = list(source.pending)
    source.pending.clear()
    settings = dispatch_settings(port, long_poll_s=30.0)
    with Dispatcher(settings, source) as dispatcher, worker_thread(port, "waiter"):
        assert eventually(lambda: bool(dispatcher.workers()))
        source.pending.extend(jobs)
        dispatcher.notify()
        assert source.done.wait(WAIT)


def test_worker_that_leaves_is_listed_as_gone() -> None:
    port = free_port()
    source = MemorySource()
    with Dispatcher(dispatch_settings(port), source) as dispatcher:
        with worker_thread(port, "brief"):
            assert source.done.wait(WAIT)
        assert eventually(lambda: [w.state for w in dispatcher.workers()] == ["gone"])
        (status,) = dispatcher.workers()
    assert status.name == "brief" and status.jobs_done == 4


def test_job_size_gives_each_live_worker_one_job() -> None:
    """The queue's JobSizer: population / live workers, rounded up, never below job_size."""
    port = free_port()
    config = CONFIG.model_copy(update={"population": 12, "job_size": 3})
    with (
        Dispatcher(dispatch_settings(port), MemorySource()) as dispatcher,
        zenoh.open(client_config(port)) as session,
    ):
        assert dispatcher.job_size(config, 0) == 3  # nobody yet: the run's own size
        tokens = [session.liveliness().declare_token(worker_key(n)) for n in ("a", "b", "c")]
        assert eventually(lambda: dispatcher.job_size(config, 0) == 4)
        assert dispatcher.job_size(config.model_copy(update={"job_size": 5}), 0) == 5
        assert dispatcher.job_size(config, 0, local=1) == 3  # + an in-process executor thread
        tokens.pop().undeclare()  # type: ignore[no-untyped-call]
        assert eventually(lambda: dispatcher.job_size(config, 0) == 6)
        for token in tokens:
            token.undeclare()  # type: ignore[no-untyped-call]
        assert eventually(lambda: dispatcher.job_size(config, 0) == 3)
    finer = Dispatcher(dispatch_settings(free_port(), jobs_per_worker=2), MemorySource())
    with finer, zenoh.open(client_config(int(finer.settings.listen[0].rsplit(":", 1)[1]))) as s:
        token = s.liveliness().declare_token(worker_key("a"))
        assert eventually(lambda: finer.job_size(config, 0) == 6)
        token.undeclare()  # type: ignore[no-untyped-call]


def test_a_generation_is_one_job_only_if_whoever_leases_it_gets_a_span() -> None:
    """The span threshold must hold for every live worker's speed (the slowest decides, an
    unknown one means slices) and a generation must follow: else a whole generation leased to
    a worker that gets no span keeps the others idle."""
    port = free_port()
    config = CONFIG.model_copy(update={"population": 12, "job_size": 1, "generations": 5})
    robot_steps = config.population * config.trials * config.steps
    settings = dispatch_settings(port, span_below_s=1.0, long_poll_s=0.1)
    with (
        Dispatcher(settings, MemorySource(config)) as dispatcher,
        zenoh.open(client_config(port)) as session,
    ):

        def asks(name: str, generation_s: float) -> None:
            request = JobRequest(worker=name, robot_steps_per_s=robot_steps / generation_s)
            ask(session, KEY_JOB_NEXT, encode_message(request))

        asks("a", 0.5)
        asks("b", 0.5)
        assert dispatcher.job_size(config, 0) == 12
        assert dispatcher.job_size(config, 3) == 12
        assert dispatcher.job_size(config, 4) == 6  # the last one: no span can follow
        assert dispatcher.job_size(config, 0, local=1) == 4  # executor threads never span
        token = session.liveliness().declare_token(worker_key("new"))
        assert eventually(lambda: dispatcher.job_size(config, 0) == 4)  # its speed is unknown
        token.undeclare()  # type: ignore[no-untyped-call]
        assert eventually(lambda: dispatcher.job_size(config, 0) == 12)
        asks("b", 2.0)  # now slower than the threshold
        assert dispatcher.job_size(config, 0) == 6


def test_a_worker_of_another_protocol_waits_out_the_long_poll_and_is_not_counted() -> None:
    """An old worker gets no job and no share of the cut, and its requests are held for the
    long-poll (about one a second) instead of being answered idle at once."""
    port = free_port()
    config = CONFIG.model_copy(update={"population": 12, "job_size": 3})
    source = MemorySource()
    settings = dispatch_settings(port, long_poll_s=0.3)
    with Dispatcher(settings, source) as dispatcher, zenoh.open(client_config(port)) as session:
        tokens = [session.liveliness().declare_token(worker_key(n)) for n in ("old", "new")]
        assert eventually(lambda: dispatcher.job_size(config, 0) == 6)
        old = JobRequest(worker="old", protocol=PROTOCOL - 1)
        began = time.monotonic()
        reply = decode_next_reply(_ok(ask(session, KEY_JOB_NEXT, encode_message(old))))
        assert isinstance(reply, Idle) and f"protocol {PROTOCOL}" in reply.reason
        assert time.monotonic() - began >= settings.long_poll_s * 0.9
        assert dispatcher.job_size(config, 0) == 12  # only "new" takes jobs
        assert not source.leased_by
        for token in tokens:
            token.undeclare()  # type: ignore[no-untyped-call]


def test_settings_reject_bad_values() -> None:
    with pytest.raises(ValueError):
        DispatchSettings(listen=(), connect=())
    with pytest.raises(ValueError):
        DispatchSettings(long_poll_s=0)
    with pytest.raises(ValueError, match="jobs_per_worker"):
        DispatchSettings(jobs_per_worker=0)
    settings = DispatchSettings(lease_min_s=2.0, lease_factor=10.0, lease_unknown_s=60.0)
    assert settings.lease_seconds(1000, None) == 60.0
    assert settings.lease_seconds(1000, 1000.0) == 10.0
    assert settings.lease_seconds(10, 1000.0) == 2.0


def _ok(reply: zenoh.Reply) -> bytes:
    assert reply.ok is not None, reply.err
    return reply.ok.payload.to_bytes()


@contextmanager
def started_manager(tmp_path: Path) -> Iterator[Any]:
    """A started RunManager on a fresh SQLite file, without executors (zenoh workers
    evaluate); stopped and its engine disposed on exit."""
    from server.db import make_engine, upgrade
    from server.manager import RunManager
    from server.settings import Settings

    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    manager = RunManager(engine, Settings(executors=0, housekeeping_seconds=0.1))
    manager.start()
    try:
        yield manager
    finally:
        manager.stop()
        engine.dispose()


def completed(manager: Any, run_id: int) -> bool:
    return bool(stored_run(manager, run_id).status == "completed")


def stored_run(manager: Any, run_id: int) -> Any:
    """Run `run_id` as stored now (detached from its session)."""
    from server.models import Run

    with manager.sessions.begin() as session:
        found = session.get(Run, run_id)
        assert found is not None
        session.expunge(found)
        return found


def test_queue_source_two_workers_give_the_same_best_as_local_evolve(tmp_path: Path) -> None:
    """Through the database queue and two real workers: bit-identical to `evolve`."""
    from evorobotics.evolution import evolve
    from worker.main import evaluate_slice

    config = RunConfig(population=8, generations=3, trials=1, steps=10, job_size=3, seed=4)
    port = free_port()
    with started_manager(tmp_path) as manager:
        source = QueueSource(manager.queue)
        run_id = manager.create_run(config)

        def status() -> str:
            return str(stored_run(manager, run_id).status)

        with Dispatcher(dispatch_settings(port), source) as dispatcher:
            # generations are cut per live worker (4 + 4 once both are up), run 0 as 3+3+2
            manager.queue.set_job_sizer(dispatcher.job_size)
            with (
                worker_thread(port, "one", evaluate_slice),
                worker_thread(port, "two", evaluate_slice),
            ):
                assert eventually(lambda: status() == "completed", timeout=60.0), status()
        sha = manager.best(run_id)
    assert sha == evolve(config).best.sha256


def test_quick_generations_go_out_as_spans_that_pause_resume_and_match_evolve(
    tmp_path: Path,
) -> None:
    """A generation far below `span_below_s` is one job, sent as a span: its worker evolves
    the next ones itself. Pausing ends the span; resuming starts another; the best controller
    is `evolve`'s bit for bit."""
    from evorobotics.evolution import evolve
    from worker.main import evaluate_slice

    # enough generations that the pause lands mid-run: 300 took 0.15 s and could end first
    config = RunConfig(population=8, generations=3000, trials=1, steps=10, seed=6)
    port = free_port()
    with started_manager(tmp_path) as manager:

        def run() -> Any:
            return stored_run(manager, run_id)

        settings = dispatch_settings(port, span_below_s=10.0)
        with Dispatcher(settings, QueueSource(manager.queue)) as dispatcher:
            manager.queue.set_job_sizer(dispatcher.job_size)
            with (
                worker_thread(port, "one", evaluate_slice),
                worker_thread(port, "two", evaluate_slice),
            ):
                assert eventually(lambda: len(dispatcher.workers()) == 2, timeout=WAIT)
                run_id = manager.create_run(config)
                assert eventually(lambda: run().generation >= 5, timeout=60.0)
                manager.pause(run_id)
                # the generation in flight may still be written; nothing is leased after it
                assert eventually(lambda: manager.queue.counts()["leased"] == 0, timeout=WAIT)
                manager.queue.flush()
                paused_at = run().generation
                spans = dispatcher.spans_served
                assert paused_at < config.generations and spans >= 1
                manager.resume(run_id)
                assert eventually(lambda: run().status == "completed", timeout=60.0)
                assert dispatcher.spans_served > spans
        sha = manager.best(run_id)
    assert sha == evolve(config).best.sha256


@pytest.mark.parametrize("kind", ["zenoh", "shared"])
def test_a_span_split_with_an_idle_worker_matches_evolve(tmp_path: Path, kind: str) -> None:
    """With teams on, the span's worker splits every generation with the idle one (over
    zenoh: each evaluates its slice, both tell and ask; in shared memory: both take chunks of
    what the leader asked): the run is `evolve`'s bit for bit and only the leader's results
    reach the server."""
    from evorobotics.evolution import evolve
    from worker.main import evaluate_slice

    config = RunConfig(population=8, generations=200, trials=1, steps=10, seed=8)
    port = free_port()
    with started_manager(tmp_path) as manager:

        def status() -> str:
            return str(stored_run(manager, run_id).status)

        slices = {"team_slice_s": 1e-9, "shared_slice_s": 0.0}
        if kind == "shared":
            slices = {"team_slice_s": 0.0, "shared_slice_s": 1e-9}
        settings = dispatch_settings(port, span_below_s=10.0, **slices)
        with Dispatcher(settings, QueueSource(manager.queue)) as dispatcher:
            manager.queue.set_job_sizer(dispatcher.job_size)
            with (
                worker_thread(port, "one", evaluate_slice) as one,
                worker_thread(port, "two", evaluate_slice) as two,
            ):
                assert eventually(lambda: len(dispatcher.workers()) == 2, timeout=WAIT)
                # only a worker that has evaluated (its kernels compiled) joins a team: a
                # one-generation run of two slices (again if one worker took both) first
                warm = RunConfig(population=8, generations=1, trials=1, steps=10, seed=1)
                for _ in range(10):
                    if all(w.robot_steps_per_s for w in dispatcher.workers()):
                        break
                    finished = partial(completed, manager, manager.create_run(warm))
                    assert eventually(finished, timeout=WAIT)
                assert all(w.robot_steps_per_s for w in dispatcher.workers())
                before = {w.name: w.jobs_done for w in dispatcher.workers()}
                run_id = manager.create_run(config)
                assert eventually(lambda: status() == "completed", timeout=60.0), status()
                served = {w.name: w.jobs_done - before[w.name] for w in dispatcher.workers()}
            assert dispatcher.teams_served >= 1
            shared = dispatcher.shared_teams_served
            assert shared == (dispatcher.teams_served if kind == "shared" else 0)
            # the server counted the leader's generations (generation 0 may go out in two
            # slices); the member evaluated its half of them too, but reported none
            assert config.generations <= sum(served.values()) <= config.generations + 1
            assert min(one.jobs_done, two.jobs_done) > min(served.values()) + 10
        sha = manager.best(run_id)
    assert sha == evolve(config).best.sha256


@pytest.mark.parametrize(("machines", "shared"), [(("m1", "m1"), True), (("m1", "m2"), False)])
def test_a_span_is_split_in_shared_memory_only_by_workers_of_one_machine(
    tmp_path: Path, machines: tuple[str, str], shared: bool
) -> None:
    """Two measured workers wait on held requests when a run starts: its span goes to one,
    with the other as member; in shared memory only if both named the same machine."""
    config = RunConfig(population=6, generations=50, trials=1, steps=5, seed=2)
    port = free_port()
    replies: dict[str, object] = {}
    with (
        started_manager(tmp_path) as manager,
        Dispatcher(
            dispatch_settings(
                port, span_below_s=10.0, long_poll_s=4.0, team_slice_s=0.005, shared_slice_s=0.001
            ),
            QueueSource(manager.queue),
        ) as dispatcher,
        zenoh.open(client_config(port)) as session,
    ):
        manager.queue.set_job_sizer(dispatcher.job_size)

        def request(name: str, machine: str) -> None:
            asking = JobRequest(worker=name, host="h", machine=machine, robot_steps_per_s=1e3)
            replies[name] = decode_next_reply(
                _ok(ask(session, KEY_JOB_NEXT, encode_message(asking)))
            )

        threads = [
            threading.Thread(target=request, args=(f"w{i}", machine))
            for i, machine in enumerate(machines)
        ]
        for thread in threads:
            thread.start()
        assert eventually(lambda: len(dispatcher.workers()) == 2, timeout=WAIT)
        manager.create_run(config)
        for thread in threads:
            thread.join(WAIT)
    jobs = sorted((j for j in replies.values() if isinstance(j, Job)), key=lambda j: j.member)
    assert [(j.member, j.shared, len(j.team)) for j in jobs] == [(0, shared, 2), (1, shared, 2)]
    assert dispatcher.shared_teams_served == int(shared)


def test_a_worker_whose_ga_differs_has_its_span_refused_and_gets_no_more(
    tmp_path: Path,
) -> None:
    """A hand-driven worker sends generation 0 of its span right and generation 1 with the
    digest of other genomes: generation 0 counts, generation 1 is a failed attempt (retried,
    not recorded), and the worker's next job is an ordinary one with genomes asked here."""
    from evorobotics.ga import GAParams, GAState, ga_rng, tell
    from evorobotics.ga import ask as ga_ask
    from evorobotics.layout import layout
    from server.db import make_engine, upgrade
    from server.manager import RunManager
    from server.settings import Settings

    config = RunConfig(population=6, generations=5, trials=1, steps=5, seed=2)
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    manager = RunManager(engine, Settings(executors=0, max_attempts=3))
    manager.queue.set_job_sizer(lambda c, _g: c.population)
    port = free_port()
    run_id = manager.create_run(config)
    settings = dispatch_settings(port, span_below_s=10.0)
    request = encode_message(JobRequest(worker="skewed", robot_steps_per_s=1e6))
    try:
        with (
            Dispatcher(settings, QueueSource(manager.queue)) as dispatcher,
            zenoh.open(client_config(port)) as session,
        ):
            token = session.liveliness().declare_token(worker_key("skewed"))
            span = decode_next_reply(_ok(ask(session, KEY_JOB_NEXT, request)))
            assert isinstance(span, Job) and span.span == 5 and span.state is not None
            params, lay = GAParams.from_config(config), layout(config.network_spec)
            fitness0 = fake_fitness(span.genomes)
            state = tell(span.genomes, fitness0, GAState.from_arrays(span.state), params)[0]
            genomes1 = ga_ask(ga_rng(config.seed, 1), state, params, lay)[0]
            results = [
                Result(
                    JobKey(run_id=run_id, generation=g, index=0),
                    "skewed",
                    fake_fitness(genomes),
                    np.zeros((6, 1, 4)),
                    start=0,
                    stop=6,
                    digest=genome_digest(genomes),
                )
                for g, genomes in ((0, span.genomes), (1, genomes1 + 1.0))
            ]
            reply = ask(session, KEY_JOB_RESULT, encode_span_results(results))
            assert decode_ack(_ok(reply)).key == results[0].key
            with manager.sessions() as db:
                run = crud.get_run(db, run_id=run_id)
                assert run is not None and run.status == "running"
            assert manager.queue.totals()["requeued"] == 1  # generation 1, retried
            following = decode_next_reply(_ok(ask(session, KEY_JOB_NEXT, request)))
            assert isinstance(following, Job) and following.key.generation == 1
            assert following.span == 1 and following.state is None
            assert following.genomes.tobytes() == genomes1.tobytes()
            assert dispatcher.spans_served == 1
            token.undeclare()  # type: ignore[no-untyped-call]
        manager.queue.flush()
        with manager.sessions() as db:
            generations = crud.list_generations(db, run_id=run_id)
            assert [g.generation for g in generations] == [0]
    finally:
        engine.dispose()


def test_a_worker_stopped_with_requests_in_flight_delivers_its_job_and_loses_none() -> None:
    """Protocol 9, stopping (SIGTERM): the job in evaluation is delivered once the replies in
    flight are read; the jobs those replies carried lapse with the worker's token and another
    worker finishes the generation, every job counted once."""
    port = free_port()
    source = MemorySource(CONFIG.model_copy(update={"population": 60}))  # 20 jobs
    stop = threading.Event()
    calls: list[int] = []

    def quits_at_the_fifth(
        config: RunConfig, generation: int, genomes: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        calls.append(generation)
        if len(calls) == 5:
            stop.set()
        return fake_evaluator(config, generation, genomes)

    settings = WorkerSettings(
        connect=(f"tcp/127.0.0.1:{port}",), name="quitter", backoff_max_s=0.2, request_timeout_s=5.0
    )
    with Dispatcher(dispatch_settings(port), source) as dispatcher:
        stats = run_worker(settings, stop, evaluator=quits_at_the_fifth)
        assert stats.jobs_done == 5 and len(source.fitness) == 5 and dispatcher.pipelined > 0
        assert source.wait_for(lambda: len(source.pending) == 15)  # released: token gone
        with worker_thread(port, "finisher"):
            assert source.done.wait(WAIT)
        assert dispatcher.results_accepted == 20 and dispatcher.results_dropped == 0
    assert np.array_equal(source.all_fitness(), fake_fitness(source.genomes))
