"""The worker process: invalid jobs, failing evaluators, late servers, server restarts,
signals, the real science. Servers are real: a zenoh router whose queryables answer by hand,
or the real dispatcher over the real scheduler."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
import zenoh

from evorobotics.evaluate import evaluate
from evorobotics.evolution import RunLoop
from schemas.run import RunConfig
from schemas.wire import (
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    Ack,
    Idle,
    JobKey,
    Result,
    WireError,
    decode,
    encode,
    encode_frame,
)
from server.runs.dispatch import Dispatcher, DispatchSettings
from server.runs.outbox import Written
from server.runs.scheduler import Scheduler
from tests.helpers import (
    WAIT,
    eventually,
    fake_components,
    fake_evaluator,
    fake_fitness,
    free_port,
    router_config,
    worker_thread,
)
from worker.main import (
    EvaluationError,
    Evaluator,
    WorkerError,
    WorkerSettings,
    WorkerStats,
    evaluate_slice,
)

CONFIG = RunConfig(population=8, job_size=3, generations=3, trials=2, steps=5)
W = CONFIG.network_spec.weight_count
KEY = JobKey(run_id=9, generation=2, index=0)


def serve_one_job(
    frame: bytes, evaluator: Evaluator = fake_evaluator, after: bytes | None = None
) -> tuple[Result, WorkerStats]:
    """A hand-made server hands `frame` to a real worker as its job (then `after`, default
    Idle, to every request) and acknowledges the first result: returned with the stats."""
    port = free_port()
    inbox: list[bytes] = []
    got = threading.Event()
    asked_again = threading.Event()

    def on_next(query: zenoh.Query) -> None:
        with query:
            if not got.is_set() and not inbox:
                query.reply(query.key_expr, frame)
                return
            if got.is_set():
                asked_again.set()  # the worker lives on after the result
            query.reply(query.key_expr, encode(Idle()) if after is None else after)

    def on_result(query: zenoh.Query) -> None:
        with query:
            assert query.payload is not None
            payload = query.payload.to_bytes()
            inbox.append(payload)
            key = decode(payload, Result).key
            query.reply(query.key_expr, encode(Ack(key=key, accepted=True)))
            got.set()

    with zenoh.open(router_config(port)) as session:
        nxt = session.declare_queryable(KEY_JOB_NEXT, on_next)
        res = session.declare_queryable(KEY_JOB_RESULT, on_result)
        try:
            with worker_thread(port, "careful", evaluator) as stats:
                assert got.wait(WAIT)
                assert asked_again.wait(WAIT)
        finally:
            nxt.undeclare()  # type: ignore[no-untyped-call]
            res.undeclare()  # type: ignore[no-untyped-call]
    return decode(inbox[0], Result), stats


def job_frame(key: JobKey = KEY, genomes: np.ndarray | None = None, **header: Any) -> bytes:
    """A job frame by hand (so it can be invalid): rows 0..3 of CONFIG by default."""
    genomes = np.ones((3, W)) if genomes is None else genomes
    fields = {"kind": "job", "key": key.model_dump(), "start": 0, "stop": len(genomes),
              "lease_s": 5.0, "config": CONFIG.model_dump(mode="json")}  # fmt: skip
    arrays = {"genomes": genomes}
    arrays |= {f"state.{k}": v for k, v in header.pop("state", {}).items()}
    return encode_frame(fields | header, arrays)


def test_invalid_job_is_reported_as_an_error_result() -> None:
    """A hand-made server hands out a job with NaN genomes; the worker answers with an error,
    then drops a malformed reply and lives on."""
    result, stats = serve_one_job(job_frame(genomes=np.full((3, W), np.nan)), after=b"junk")
    assert result.key == KEY and result.fitness is None and result.worker == "careful"
    assert result.error is not None and "NaN" in result.error
    assert (stats.jobs_done, stats.errors) == (0, 1)


def test_a_valid_job_is_evaluated_and_delivered() -> None:
    genomes = np.random.default_rng(3).normal(size=(3, W))
    result, stats = serve_one_job(job_frame(genomes=genomes))
    assert result.error is None and (result.start, result.stop) == (0, 3)
    assert result.fitness is not None and result.components is not None
    assert result.fitness.tobytes() == fake_fitness(genomes)[np.newaxis].tobytes()
    assert (
        result.components.tobytes() == fake_components(genomes, CONFIG.trials)[np.newaxis].tobytes()
    )
    assert result.robot_steps_per_s > 0 and result.digests == ()
    assert (stats.jobs_done, stats.errors) == (1, 0)


def wrong_shape(config: RunConfig, generation: int, genomes: np.ndarray) -> Any:
    n = len(genomes)
    return np.zeros(n + 1), np.zeros((n, config.trials, 4)), np.zeros((n, 4))


def wrong_components(config: RunConfig, generation: int, genomes: np.ndarray) -> Any:
    n = len(genomes)
    return np.zeros(n), np.zeros((n, config.trials)), np.zeros((n, 4))


def wrong_descriptors(config: RunConfig, generation: int, genomes: np.ndarray) -> Any:
    n = len(genomes)
    return np.zeros(n), np.zeros((n, config.trials, 4)), np.zeros((n, 2))


def nan_fitness(config: RunConfig, generation: int, genomes: np.ndarray) -> Any:
    n = len(genomes)
    return np.full(n, np.nan), np.zeros((n, config.trials, 4)), np.zeros((n, 4))


def not_arrays(config: RunConfig, generation: int, genomes: np.ndarray) -> Any:
    return "fitness", None


def raises(config: RunConfig, generation: int, genomes: np.ndarray) -> Any:
    raise RuntimeError("the simulator broke")


@pytest.mark.parametrize(
    ("evaluator", "text"),
    [
        (wrong_shape, "EvaluationError: evaluator returned (4,)"),
        (wrong_components, "EvaluationError"),
        (wrong_descriptors, "EvaluationError"),
        (nan_fitness, "EvaluationError: evaluator returned non-finite fitness"),
        (not_arrays, "ValueError"),
        (raises, "RuntimeError: the simulator broke"),
    ],
)
def test_a_failing_evaluator_gives_an_error_result_not_a_crash(
    evaluator: Evaluator, text: str
) -> None:
    result, stats = serve_one_job(job_frame(), evaluator)
    assert result.key == KEY and (result.start, result.stop) == (0, 3)
    assert result.fitness is None and result.error is not None and text in result.error
    assert (stats.jobs_done, stats.errors) == (0, 1)
    assert issubclass(EvaluationError, WorkerError)


@contextmanager
def served(port: int, run_id: int, config: RunConfig = CONFIG) -> Iterator[Any]:
    """A real dispatcher over a real scheduler serving one run; yields the dispatcher, the
    scheduler and `take()`, every generation told so far."""
    scheduler = Scheduler()
    scheduler.add(run_id, RunLoop(config), running=True)
    told: list[Written] = []

    def take() -> list[Written]:
        taken = scheduler.take_told()
        scheduler.written(taken)  # as the run manager does once it has stored them
        told.extend(taken)
        return told

    settings = DispatchSettings(listen=(f"tcp/127.0.0.1:{port}",), long_poll_s=0.2)
    with Dispatcher(settings, scheduler) as dispatcher:
        yield dispatcher, scheduler, take


def finished(take: Any, generations: int) -> bool:
    told = take()
    return len(told) == generations and told[-1].last


def test_worker_started_before_the_server_waits_and_survives_a_restart() -> None:
    port = free_port()
    with worker_thread(port, "patient", fake_evaluator) as stats:
        with served(port, 1) as (_, _, take):
            assert eventually(lambda: finished(take, CONFIG.generations), WAIT)
        with served(port, 2) as (dispatcher, scheduler, take):
            assert eventually(lambda: finished(take, CONFIG.generations), WAIT)
            assert [w.name for w in scheduler.workers()] == ["patient"]
            assert dispatcher.alive()
    told = take()
    assert [w.told.generation for w in told] == list(range(CONFIG.generations))
    for written in told:
        assert written.run_id == 2
        expected = fake_fitness(written.told.genomes)
        assert written.told.fitness.tobytes() == expected.tobytes()
    assert stats.jobs_done >= 2 * CONFIG.generations and stats.errors == 0


def test_real_evaluation_matches_evaluate_bit_for_bit() -> None:
    """The default evaluator is evorobotics.evaluate over the whole slice."""
    port = free_port()
    config = CONFIG.model_copy(update={"generations": 1})
    with (
        served(port, 1, config) as (_, _, take),
        worker_thread(port, "sci", evaluate_slice) as stats,
    ):
        assert eventually(lambda: finished(take, 1), 120.0)
    told = take()[0].told
    expected = evaluate(config, 0, told.genomes)
    assert told.fitness.tobytes() == expected.fitness.tobytes()
    assert told.components is not None
    assert told.components.tobytes() == expected.components.tobytes()
    assert stats.jobs_done >= 1


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_colony_worker_exits_cleanly_on_signal(signum: int) -> None:
    """`colony worker` with no server reachable: a signal ends its retry loop with status 0."""
    port = free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [os.path.join(os.path.dirname(sys.executable), "colony"), "worker", "--connect",
         f"tcp/127.0.0.1:{port}", "--name", "sig"],
        stderr=subprocess.PIPE, stdout=subprocess.PIPE, env=env, text=True,
    )  # fmt: skip
    try:
        assert proc.stderr is not None
        for line in proc.stderr:
            if "no router" in line:
                break
        proc.send_signal(signum)
        out, _ = proc.communicate(timeout=WAIT)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0
    assert "worker sig: 0 evaluations in 0 jobs" in out


def test_settings_validate() -> None:
    for bad in (
        {"name": "a/b"},
        {"name": ""},
        {"connect": ()},
        {"backoff_max_s": 0},
        {"backoff_initial_s": -1.0},
        {"request_timeout_s": 0.0},
    ):
        with pytest.raises(ValueError):
            WorkerSettings(**bad)
    settings = WorkerSettings(name="ok-1", connect=("tcp/127.0.0.1:1",))
    assert settings.zenoh_config() is not None
    assert issubclass(WireError, ValueError)


def ranked_state(generation: int, rows: int) -> dict[str, np.ndarray]:
    """A GA state of `generation` ranking `rows` genomes (the run has CONFIG.population)."""
    state = {
        "generation": np.array(generation),
        "n_weights": np.array(W),
        "ranked": np.zeros((rows, W)),
        "ranked_fitness": np.zeros(rows),
    }
    if generation >= 2:
        state["elite_k2"] = np.zeros(W)
    return state


@pytest.mark.parametrize(
    ("generation", "state", "reason"),
    [
        (0, {"generation": np.array(0), "n_weights": np.array(W + 1)}, "weights"),
        (0, {"generation": np.array(1), "n_weights": np.array(W)}, "generation 1"),
        (0, {"generation": np.array(0)}, "n_weights"),
        (1, {"generation": np.array(0), "n_weights": np.array(W)}, "state of generation 0"),
        (1, ranked_state(1, 3), "population"),  # ranks 3 genomes of 8
    ],
)
def test_a_span_whose_ga_state_does_not_fit_is_an_error_result_not_a_crash(
    generation: int, state: dict[str, np.ndarray], reason: str
) -> None:
    key = JobKey(run_id=9, generation=generation, index=0)
    frame = job_frame(key, np.zeros((CONFIG.population, W)), span=2, state=state)
    result, stats = serve_one_job(frame)
    assert result.key == key and result.fitness is None
    assert result.error is not None and "GA state" in result.error and reason in result.error
    assert (stats.jobs_done, stats.errors) == (0, 1)


def test_a_span_is_evolved_by_the_run_loop_and_counts_every_generation(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A fast worker gets spans from the real scheduler: the run's generations are the ones
    the run loop asks in this process, whoever evaluated them."""
    caplog.set_level(logging.INFO, logger="server.runs.dispatch")
    port = free_port()
    config = CONFIG.model_copy(update={"generations": 6})
    with (
        served(port, 1, config) as (_, _, take),
        worker_thread(port, "spanner", fake_evaluator) as stats,
    ):
        assert eventually(lambda: finished(take, config.generations), WAIT)
    loop = RunLoop(config)
    for written in take():
        genomes = loop.ask()
        assert written.told.genomes.tobytes() == genomes.tobytes()
        loop.tell(fake_fitness(genomes))
    assert stats.errors == 0 and stats.jobs_done >= config.generations
    assert any("as a span of" in record.getMessage() for record in caplog.records)
