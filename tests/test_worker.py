"""The worker process: invalid jobs, late servers, server restarts, signals, the real science."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading

import numpy as np
import pytest
import zenoh

from evorobotics.evaluate import evaluate
from schemas.wire import (
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    Ack,
    Idle,
    JobKey,
    Result,
    WireError,
    decode_result,
    encode_frame,
    encode_message,
)
from server.dispatch import Dispatcher
from tests.helpers import eventually, free_port
from tests.test_dispatch import (
    CONFIG,
    WAIT,
    MemorySource,
    W,
    dispatch_settings,
    fake_fitness,
    worker_thread,
)
from worker.main import WorkerSettings, WorkerStats, evaluate_slice

KEY = JobKey(run_id=9, generation=2, index=0)


def router_config(port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def serve_one_job(
    frame: bytes, key: JobKey, after: bytes | None = None
) -> tuple[Result, WorkerStats]:
    """A hand-made server hands `frame` to a real worker as its job (then `after`, default
    Idle, to every request) and acknowledges the first result: returned with the stats."""
    port = free_port()
    inbox: list[bytes] = []
    got = threading.Event()
    served = threading.Event()

    def on_next(query: zenoh.Query) -> None:
        with query:
            if not served.is_set():
                served.set()
                query.reply(KEY_JOB_NEXT, frame)
            else:
                query.reply(KEY_JOB_NEXT, encode_message(Idle()) if after is None else after)

    def on_result(query: zenoh.Query) -> None:
        with query:
            assert query.payload is not None
            inbox.append(query.payload.to_bytes())
            query.reply(KEY_JOB_RESULT, encode_message(Ack(key=key, accepted=True)))
            got.set()

    with zenoh.open(router_config(port)) as session:
        nxt = session.declare_queryable(KEY_JOB_NEXT, on_next)
        res = session.declare_queryable(KEY_JOB_RESULT, on_result)
        try:
            with worker_thread(port, "careful") as stats:
                assert got.wait(WAIT)
        finally:
            nxt.undeclare()  # type: ignore[no-untyped-call]
            res.undeclare()  # type: ignore[no-untyped-call]
    return decode_result(inbox[0]), stats


def test_invalid_job_is_reported_as_an_error_result() -> None:
    """A hand-made server hands out a job with NaN genomes; the worker answers with an error."""
    nan_genomes = np.full((3, W), np.nan)
    bad = encode_frame(
        {"kind": "job", "key": KEY.model_dump(), "start": 0, "stop": 3, "lease_s": 5.0,
         "config": CONFIG.model_dump(mode="json")},
        {"genomes": nan_genomes},
    )  # fmt: skip
    result, stats = serve_one_job(bad, KEY, after=b"not a frame")  # malformed: dropped too
    assert result.key == KEY and result.fitness is None
    assert result.error is not None and "NaN" in result.error
    assert stats.jobs_done == 0


def test_worker_started_before_the_server_waits_and_survives_a_restart() -> None:
    port = free_port()
    first = MemorySource()
    with worker_thread(port, "patient") as stats:
        with Dispatcher(dispatch_settings(port), first):
            assert first.done.wait(WAIT)
        second = MemorySource(run_id=2)
        with Dispatcher(dispatch_settings(port), second) as dispatcher:
            assert second.done.wait(WAIT)
            assert eventually(lambda: [w.name for w in dispatcher.workers()] == ["patient"])
    assert stats.jobs_done == 8
    assert np.array_equal(second.all_fitness(), fake_fitness(second.genomes))


def test_real_evaluation_matches_evaluate_bit_for_bit() -> None:
    """The default evaluator is evorobotics.evaluate over the whole slice."""
    port = free_port()
    source = MemorySource()
    with Dispatcher(dispatch_settings(port), source), worker_thread(port, "sci", evaluate_slice):
        assert source.done.wait(60.0)
    expected = evaluate(CONFIG, 0, source.genomes[0:3]).fitness
    assert source.fitness[0].tobytes() == expected.tobytes()


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_colony_worker_exits_cleanly_on_signal(signum: int) -> None:
    """`colony worker` with no server reachable: a signal ends its retry loop with status 0."""
    port = free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [os.path.join(os.path.dirname(sys.executable), "colony"), "worker", "--connect", f"tcp/127.0.0.1:{port}",
         "--name", "sig"],
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
    assert "worker sig: 0 jobs done" in out


def test_settings_validate() -> None:
    with pytest.raises(ValueError):
        WorkerSettings(name="a/b")
    with pytest.raises(ValueError):
        WorkerSettings(connect=())
    with pytest.raises(ValueError):
        WorkerSettings(backoff_max_s=0)
    assert issubclass(WireError, ValueError)


@pytest.mark.parametrize(
    ("state", "reason"),
    [
        ({"generation": np.array(0), "n_weights": np.array(W + 1)}, "weights"),
        ({"generation": np.array(1), "n_weights": np.array(W)}, "generation 1"),
        ({"generation": np.array(0)}, "unusable"),
    ],
)
def test_a_span_whose_ga_state_does_not_fit_is_an_error_result_not_a_crash(
    state: dict[str, np.ndarray], reason: str
) -> None:
    config = CONFIG.model_copy(update={"generations": 3})
    key = JobKey(run_id=9, generation=0, index=0)
    arrays = {"genomes": np.zeros((config.population, W))}
    arrays |= {f"state.{name}": value for name, value in state.items()}
    span = encode_frame(
        {"kind": "job", "key": key.model_dump(), "start": 0, "stop": config.population,
         "lease_s": 5.0, "span": 3, "config": config.model_dump(mode="json")},
        arrays,
    )  # fmt: skip
    result, stats = serve_one_job(span, key)
    assert result.key == key and result.fitness is None
    assert result.error is not None and "GA state" in result.error and reason in result.error
    assert stats.jobs_done == 0
