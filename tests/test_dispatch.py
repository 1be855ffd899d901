"""The dispatcher over real zenoh on 127.0.0.1 (multicast scouting off): the real Scheduler
behind it, real workers (`run_worker` in threads) or a hand-driven zenoh client in front; once
the whole server (uvicorn, its router, an honest worker) against a rogue client."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh

from evorobotics.evolution import RunLoop, evaluate_population, evolve
from evorobotics.ga import GAState
from schemas.run import RunConfig
from schemas.wire import (
    KEY_WORKERS,
    PROTOCOL,
    Ack,
    Idle,
    Job,
    JobKey,
    JobRequest,
    Result,
    decode_next_reply,
    decode_result_reply,
    encode,
    encode_frame,
    genome_digest,
    next_key,
    result_key,
    worker_key,
)
from server.core.settings import Settings
from server.runs.dispatch import Dispatcher, DispatchSettings
from server.runs.outbox import Written
from server.runs.policy import Policy
from server.runs.scheduler import Scheduler
from tests.helpers import (
    as_worker,
    dispatch_settings,
    eventually,
    fake_evaluator,
    fake_fitness,
    free_port,
    gone_worker,
    reference,
    same_generations,
    serving,
    wait_status,
    worker_thread,
    zenoh_client,
)
from worker.main import Evaluator, WorkerSettings, WorkerStats, evaluate_slice, run_worker

CONFIG = RunConfig(population=12, job_size=3, generations=2, trials=2, steps=5)
WAIT = 20.0
LONG_POLL_S = 0.3
FAST = 1e9


class Served:
    """A scheduler behind a dispatcher on a free loopback port."""

    def __init__(self, scheduler: Scheduler, dispatcher: Dispatcher, port: int) -> None:
        self.scheduler, self.dispatcher, self.port = scheduler, dispatcher, port
        self.told: list[Written] = []

    def wait_told(self, predicate: Callable[[list[Written]], bool], timeout: float = WAIT) -> bool:
        def check() -> bool:
            taken = self.scheduler.take_told()
            self.scheduler.written(taken)  # as the run manager does once it has stored them
            self.told += taken
            return predicate(self.told)

        return eventually(check, timeout=timeout)

    def wait_run_done(self, timeout: float = WAIT) -> list[Written]:
        assert self.wait_told(lambda told: bool(told) and told[-1].last, timeout)
        return self.told


@contextmanager
def serve(policy: Policy | None = None, long_poll_s: float = LONG_POLL_S) -> Iterator[Served]:
    scheduler = Scheduler(policy)
    port = free_port()
    with Dispatcher(dispatch_settings(port, long_poll_s=long_poll_s), scheduler) as dispatcher:
        yield Served(scheduler, dispatcher, port)
        assert dispatcher.alive()  # whatever happened, it still serves


@contextmanager
def workers(
    port: int, names: list[str], evaluator: Evaluator = fake_evaluator
) -> Iterator[list[WorkerStats]]:
    """Real workers in threads; stopped (and joined) on exit; their stats."""
    stop = threading.Event()
    stats: list[WorkerStats] = []

    def run(name: str) -> None:
        settings = WorkerSettings(connect=(f"tcp/127.0.0.1:{port}",), name=name, backoff_max_s=0.2)
        stats.append(run_worker(settings, stop, evaluator=evaluator))

    threads = [threading.Thread(target=run, args=(n,), daemon=True) for n in names]
    for thread in threads:
        thread.start()
    try:
        yield stats
    finally:
        stop.set()
        for thread in threads:
            thread.join(WAIT)
        assert not any(thread.is_alive() for thread in threads)


def replies(session: zenoh.Session, key: str, payload: bytes) -> list[zenoh.Reply]:
    return list(session.get(key, payload=payload, timeout=WAIT))


def ok(found: list[zenoh.Reply]) -> bytes:
    assert len(found) == 1 and found[0].ok is not None, found
    return found[0].ok.payload.to_bytes()


def ask_next(session: zenoh.Session, worker: str, **fields: object) -> Job | Idle:
    """A job request as `worker`, its liveliness token declared first."""
    as_worker(session, worker)
    request = JobRequest(worker=worker, **fields)
    return decode_next_reply(ok(replies(session, next_key(worker), encode(request))))


def send(session: zenoh.Session, result: Result) -> tuple[Ack, Job | None]:
    return decode_result_reply(ok(replies(session, result_key(result.worker), encode(result))))


def result_of(job: Job, worker: str, genomes: np.ndarray | None = None, **update: object) -> Result:
    genomes = job.genomes if genomes is None else genomes
    fitness, components, descriptors = fake_evaluator(job.config, job.key.generation, genomes)
    return Result(
        key=job.key,
        worker=worker,
        start=job.start,
        stop=job.stop,
        fitness=fitness[None],
        components=components[None],
        descriptors=descriptors[None],
        **update,
    )


# ------------------------------------------------------------------------------------------------


def test_two_workers_finish_a_run_each_job_exactly_once() -> None:
    with serve() as served, workers(served.port, ["w1", "w2"]) as stats:
        assert eventually(lambda: len(served.scheduler.workers()) == 2, timeout=WAIT)
        served.scheduler.add(1, RunLoop(CONFIG), running=True)
        told = served.wait_run_done()
        totals = served.scheduler.totals()
    same_generations(told, reference(CONFIG))
    assert totals["duplicates_dropped"] == 0 and totals["requeued"] == 0
    assert totals["done"] == totals["leased"] == sum(s.jobs_done for s in stats)
    assert all(s.errors == 0 for s in stats)


def test_malformed_messages_are_dropped_and_serving_goes_on() -> None:
    with serve() as served, zenoh_client(served.port) as session:
        bad = [
            (next_key("w"), b"garbage"),
            (result_key("w"), b""),
            (next_key("w"), encode(Idle(reason="not a request"))),
            (result_key("w"), encode(JobRequest(worker="w"))),
            (next_key("w"), encode_frame({"kind": "next", "worker": "bad name!"})),
            (next_key("w"), encode(JobRequest(worker="someone-else"))),
        ]
        for key, payload in bad:
            found = replies(session, key, payload)
            assert len(found) == 1 and found[0].err is not None
            assert b"malformed" in found[0].err.payload.to_bytes()
        token = session.liveliness().declare_token(KEY_WORKERS.replace("*", "x" * 200))
        assert eventually(lambda: served.dispatcher.malformed == len(bad) + 1, timeout=WAIT)
        token.undeclare()  # type: ignore[no-untyped-call]
        served.scheduler.add(1, RunLoop(CONFIG), running=True)
        job = ask_next(session, "w")
        assert isinstance(job, Job)
        ack, _ = send(session, result_of(job, "w"))
        assert ack.accepted
        assert served.dispatcher.alive()


@pytest.mark.parametrize("how", ["undeclare", "close"])
def test_a_vanished_worker_releases_its_job_at_once_and_its_late_result_is_dropped(
    how: str,
) -> None:
    with serve() as served, zenoh_client(served.port) as other:
        served.scheduler.add(1, RunLoop(CONFIG), running=True)
        with zenoh_client(served.port) as session:
            as_worker(session, "v")
            assert eventually(lambda: [w.name for w in served.scheduler.workers()] == ["v"])
            job = ask_next(session, "v")
            assert isinstance(job, Job) and job.lease_s >= 60.0
            assert served.scheduler.counts()["leased"] == 1
            began = time.monotonic()
            if how == "undeclare":
                gone_worker(session, "v")
            else:
                session.close()  # type: ignore[no-untyped-call]
            assert eventually(lambda: served.scheduler.counts()["leased"] == 0, timeout=WAIT)
            assert time.monotonic() - began < job.lease_s
            assert [w.state for w in served.scheduler.workers()] == ["gone"]
        again = ask_next(other, "taker")
        assert isinstance(again, Job) and again.key == job.key
        ack, _ = send(other, result_of(job, "v"))  # the vanished worker's, arriving late
        assert not ack.accepted and "no liveliness token" in ack.reason
        assert send(other, result_of(again, "taker"))[0].accepted


def test_a_held_request_is_served_as_soon_as_jobs_appear() -> None:
    with serve(long_poll_s=10.0) as served, zenoh_client(served.port) as session:
        request = encode(JobRequest(worker="waiting"))
        began = time.monotonic()
        pending = session.get(next_key("waiting"), payload=request, timeout=WAIT)
        as_worker(session, "waiting")  # after its request: held until the token comes
        assert eventually(lambda: len(served.scheduler.workers()) == 1)
        served.scheduler.add(1, RunLoop(CONFIG), running=True)  # notifies the dispatcher
        reply = decode_next_reply(ok(list(pending)))
        assert isinstance(reply, Job) and reply.key.run_id == 1
        assert time.monotonic() - began < 5.0  # not the 10 s long-poll


def test_names_without_a_liveliness_token_are_leased_nothing_and_never_listed() -> None:
    """Issue 38, attack 2: one request from a name that never declared a token held a lease
    for 120 s and stopped the run, and 400 such names stayed live workers for good (spans off).
    Now they wait out the long-poll, are answered idle saying why, and count for nothing."""
    with serve(long_poll_s=0.3) as served, zenoh_client(served.port) as session:
        served.scheduler.add(1, RunLoop(CONFIG), running=True)
        phantoms = [f"phantom-{i}" for i in range(40)]
        pending = [
            session.get(next_key(n), payload=encode(JobRequest(worker=n)), timeout=WAIT)
            for n in phantoms
        ]
        answers = [decode_next_reply(ok(list(p))) for p in pending]
        assert all(isinstance(a, Idle) and "no liveliness token" in a.reason for a in answers)
        ack, _ = send(session, result_of(Job(
            key=JobKey(run_id=1, generation=0, index=0), start=0, stop=3, config=CONFIG,
            genomes=RunLoop(CONFIG).ask()[:3], lease_s=10.0,
        ), "phantom-0"))  # fmt: skip
        assert not ack.accepted and "no liveliness token" in ack.reason
        assert served.scheduler.workers() == [] and served.scheduler.counts()["leased"] == 0
        job = ask_next(session, "honest")
        assert isinstance(job, Job) and send(session, result_of(job, "honest"))[0].accepted
        assert [w.name for w in served.scheduler.workers()] == ["honest"]


def test_names_that_hold_a_token_but_never_ask_do_not_cut_generations() -> None:
    """Issue 38, attack 2: one credential declaring tokens for 40 names it never asks with
    made every generation 40 jobs for the one worker that works. Only names that ask count."""
    with serve() as served, zenoh_client(served.port) as session:
        assert isinstance(ask_next(session, "honest"), Idle)  # it asks: it works here
        for i in range(40):
            as_worker(session, f"rogue.p-{i}")
        assert eventually(lambda: len(served.scheduler.workers()) == 41)
        served.scheduler.add(1, RunLoop(CONFIG), running=True)
        job = ask_next(session, "honest")
        assert isinstance(job, Job) and (job.start, job.stop) == (0, CONFIG.population)


def test_through_the_server_tokenless_names_and_absurd_speeds_change_no_run(
    tmp_path: Path,
) -> None:
    """Issue 38, attack 2, through the real server: a rogue asks under 20 names that never
    declare a token (answered idle, never listed), then under one that does while claiming 0
    and 1e-300 robot-steps/s (leased by measured speed, never past `lease_max_seconds`); with
    an honest worker the run tells `colony evolve`'s generations."""
    config = {"population": 12, "generations": 4, "trials": 2, "steps": 10, "job_size": 3}
    zenoh_port = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zenoh_port}"],
        workers=0,
        housekeeping_seconds=0.2,
    )
    with (
        serving(settings) as (url, _app),
        httpx.Client(base_url=url, timeout=WAIT) as client,
        zenoh_client(zenoh_port) as rogue,
    ):
        run_id = client.post("/api/runs", json=config).json()["id"]
        phantoms = [f"phantom-{i}" for i in range(20)]
        pending = [
            rogue.get(next_key(n), payload=encode(JobRequest(worker=n)), timeout=WAIT)
            for n in phantoms
        ]
        answers = [decode_next_reply(ok(list(p))) for p in pending]
        assert all(isinstance(a, Idle) and "no liveliness token" in a.reason for a in answers)
        leases = []
        for speed in (0.0, 1e-300, 0.0):
            job = ask_next(rogue, "claimer", robot_steps_per_s=speed)
            assert isinstance(job, Job), job  # the only worker asking: a job each time
            leases.append(job.lease_s)
            f, c, d = evaluate_slice(job.config, job.key.generation, job.evaluated())
            claimed = Result(
                key=job.key, worker="claimer", start=job.start, stop=job.stop,
                checks=len(f) - (job.stop - job.start), robot_steps_per_s=speed,
                fitness=f[None], components=c[None], descriptors=d[None],
            )  # fmt: skip
            assert send(rogue, claimed)[0].accepted
        with worker_thread(zenoh_port, "honest", evaluate_slice):
            run = wait_status(client, run_id, {"completed", "failed"})
        assert run["status"] == "completed", run["error"]
        generations = client.get(f"/api/runs/{run_id}/generations").json()
        best = client.get(f"/api/runs/{run_id}/best").json()
        names = {w["name"] for w in client.get("/api/workers").json()}
    # the first before any speed is known, then the measured one, whatever it claimed
    assert leases == [settings.lease_unknown_seconds] + [settings.lease_min_seconds] * 2
    assert max(leases) <= settings.lease_max_seconds
    assert names == {"claimer", "honest"}
    local = evolve(RunConfig(**config))
    assert generations == [asdict(summary) for summary in local.history]
    assert best["sha256"] == local.best.sha256


def test_an_idle_request_is_answered_at_the_end_of_the_long_poll() -> None:
    with serve(long_poll_s=0.5) as served, zenoh_client(served.port) as session:
        began = time.monotonic()
        reply = ask_next(session, "w")
        assert isinstance(reply, Idle) and reply.reason == "no job"
        assert 0.4 < time.monotonic() - began < 5.0


def test_a_worker_of_another_protocol_waits_out_the_long_poll_and_is_not_counted() -> None:
    with serve(long_poll_s=0.5) as served, zenoh_client(served.port) as session:
        served.scheduler.add(1, RunLoop(CONFIG), running=True)
        began = time.monotonic()
        reply = ask_next(session, "old", protocol=PROTOCOL - 1)
        assert isinstance(reply, Idle) and f"protocol {PROTOCOL}" in reply.reason
        assert time.monotonic() - began >= 0.4
        assert served.scheduler.counts()["leased"] == 0
        served.scheduler.add(2, RunLoop(CONFIG), running=True)
        # no serving worker known: cut by the run's job_size, not as for one worker
        assert served.scheduler.counts()["pending"] == 2 * CONFIG.population // CONFIG.job_size


def test_spans_over_zenoh_match_evolve_bit_for_bit(caplog: pytest.LogCaptureFixture) -> None:
    config = RunConfig(population=8, generations=25, trials=1, steps=5, job_size=8, seed=3)
    caplog.set_level(logging.INFO, logger="server.runs.dispatch")
    with serve() as served, workers(served.port, ["solo"], evaluate_slice) as stats:
        assert eventually(lambda: len(served.scheduler.workers()) == 1, timeout=WAIT)
        served.scheduler.add(1, RunLoop(config), running=True)
        told = served.wait_run_done(timeout=60.0)
    assert "as a span of" in caplog.text
    assert stats[0].errors == 0
    loop = RunLoop(config)
    for w in told:
        fitness, components, descriptors = evaluate_population(config, loop.generation, loop.ask())
        assert w.told.genomes.tobytes() == loop.ask().tobytes()
        assert w.told.fitness.tobytes() == fitness.tobytes()
        loop.tell(fitness, components, descriptors)
    whole = evolve(config)
    assert [w.told.summary() for w in told] == list(whole.history)
    assert told[-1].told.genomes.tobytes() == whole.genomes.tobytes()
    assert told[-1].told.fitness.tobytes() == whole.fitness.tobytes()


def test_a_worker_whose_ga_differs_has_its_span_refused_and_gets_no_more() -> None:
    config = RunConfig(population=6, generations=5, trials=1, steps=5, seed=2)
    with serve(long_poll_s=10.0) as served, zenoh_client(served.port) as session:
        token = session.liveliness().declare_token(worker_key("skewed"))
        request = encode(JobRequest(worker="skewed", robot_steps_per_s=FAST))
        pending = session.get(next_key("skewed"), payload=request, timeout=WAIT)
        assert eventually(
            lambda: [w.robot_steps_per_s for w in served.scheduler.workers()] == [FAST]
        )
        served.scheduler.add(1, RunLoop(config), running=True)
        span = decode_next_reply(ok(list(pending)))
        assert isinstance(span, Job) and span.span == 5 and span.state is not None
        loop = RunLoop(config, GAState.from_arrays(span.state))
        genomes0 = loop.ask()
        loop.tell(fake_fitness(genomes0))
        genomes1 = loop.ask()
        first = result_of(span, "skewed", genomes0, digests=(genome_digest(genomes0),))
        assert send(session, first)[0].accepted
        current = span.model_copy(update={"key": span.key.at(1)})
        skewed = genomes1 + 1.0  # what a worker with another GA would have evaluated
        ack, _ = send(
            session, result_of(current, "skewed", skewed, digests=(genome_digest(skewed),))
        )
        assert ack.accepted and ack.reason == "error recorded"
        assert [w.told.generation for w in served.scheduler.take_told()] == [0]
        following = ask_next(session, "skewed", robot_steps_per_s=FAST)
        assert isinstance(following, Job) and following.key.generation == 1
        assert following.span == 1 and following.state is None
        assert following.genomes.tobytes() == genomes1.tobytes()
        token.undeclare()  # type: ignore[no-untyped-call]


def test_a_worker_stopped_mid_job_delivers_its_result() -> None:
    started, release = threading.Event(), threading.Event()

    def slow(
        config: RunConfig, generation: int, genomes: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        started.set()
        release.wait(WAIT)
        return fake_evaluator(config, generation, genomes)

    config = CONFIG.model_copy(update={"generations": 1})
    with serve() as served:
        served.scheduler.add(1, RunLoop(config), running=True)
        with workers(served.port, ["stopping"], slow) as stats:
            assert started.wait(WAIT)
            # the context's exit sets stop while the job is being evaluated; release it then
            threading.Timer(0.2, release.set).start()
        totals = served.scheduler.totals()
    assert stats[0].jobs_done == 1
    assert totals["done"] == 1 and totals["duplicates_dropped"] == 0
    assert served.scheduler.counts()["leased"] == 0


def test_the_dispatcher_thread_survives_a_failing_scheduler_call() -> None:
    class Flaky(Scheduler):
        def lease(self, worker: str) -> Job | None:
            if worker == "crash":
                raise RuntimeError("a bug in a scheduler call")
            return super().lease(worker)

    port = free_port()
    scheduler = Flaky()
    scheduler.add(1, RunLoop(CONFIG), running=True)
    with (
        Dispatcher(dispatch_settings(port, long_poll_s=LONG_POLL_S), scheduler) as dispatcher,
        zenoh_client(port) as session,
    ):
        request = encode(JobRequest(worker="crash"))
        pending = session.get(next_key("crash"), payload=request, timeout=WAIT)  # held: no token
        as_worker(session, "crash")  # served at its token, and the scheduler call fails
        answers = list(pending)
        assert len(answers) == 1 and answers[0].err is not None
        assert answers[0].err.payload.to_bytes() == b"server error"
        session.get(next_key("crash"), payload=request, timeout=1.0)  # asked again: fails at once
        job = ask_next(session, "fine")
        assert isinstance(job, Job)
        assert dispatcher.alive()
    assert not dispatcher.alive()  # closed


def test_settings_reject_bad_values() -> None:
    with pytest.raises(ValueError, match="endpoint"):
        DispatchSettings(listen=(), connect=())
    with pytest.raises(ValueError, match="long_poll_s"):
        DispatchSettings(long_poll_s=0.0)
    conf = dispatch_settings(free_port(), connect=("tcp/127.0.0.1:1",)).zenoh_config()
    assert "127.0.0.1:1" in conf.get_json("connect/endpoints")
