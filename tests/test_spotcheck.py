"""A rogue worker returning forged fitness cannot win a run: claims beyond the trial's physics
are refused on arrival, plausible ones are caught by the server's spot-checks.

A real server (uvicorn, SQLite in a temp dir, its zenoh router on a loopback port), an honest
worker thread evaluating for real, and a rogue: a plain zenoh client speaking the wire
protocol that answers its first job honestly, then forges every result after.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh

from evorobotics.evolution import evolve
from schemas.run import RunConfig
from schemas.wire import (
    Ack,
    Idle,
    JobRequest,
    Result,
    decode_next_reply,
    decode_result_reply,
    encode,
    next_key,
    result_key,
    worker_key,
)
from server.core.settings import Settings
from tests.helpers import (
    WAIT,
    client_config,
    eventually,
    free_port,
    plausible_forgery,
    serving,
    wait_status,
    worker_thread,
)
from worker.main import evaluate_slice

CONFIG = {"population": 16, "generations": 6, "steps": 20, "trials": 2, "job_size": 4, "seed": 5}
Claims = tuple[np.ndarray, np.ndarray, np.ndarray]
"""fitness (n,), components (n, trials, 4) and descriptors (n, 4) of a slice."""
Forgery = Callable[[RunConfig, np.ndarray, np.ndarray, np.ndarray], Claims | str]
"""(config, the real claims) -> the forged claims, or an error message to send instead."""


def beyond_physics(config: RunConfig, f: np.ndarray, c: np.ndarray, d: np.ndarray) -> Claims:
    """Issue 38's attack: two fitness values at 1.7e308."""
    f = f.copy()
    f[:2] = 1.7e308
    return f, c, d


def nan_components(config: RunConfig, f: np.ndarray, c: np.ndarray, d: np.ndarray) -> Claims:
    c = c.copy()
    c[0, 0, 0] = np.nan
    return f, c, d


def too_far(config: RunConfig, f: np.ndarray, c: np.ndarray, d: np.ndarray) -> Claims:
    """Curve lengths of a kilometre: Eq 12's k1 is 0, so the fitness still matches them."""
    c = c.copy()
    c[..., 0] = 1000.0
    return f, c, d


def off_the_maze(config: RunConfig, f: np.ndarray, c: np.ndarray, d: np.ndarray) -> Claims:
    """Descriptors are fractions of the maze (quality-diversity strategies select on them):
    one beyond it, one not a number."""
    d = d.copy()
    d[0, 0], d[-1, 3] = 7.5, np.nan
    return f, c, d


def plausibly(config: RunConfig, f: np.ndarray, c: np.ndarray, d: np.ndarray) -> Claims:
    """`plausible_forgery`: within physics, so only a spot-check tells it from the truth."""
    return (*plausible_forgery(config, c), d)


@contextmanager
def rogue_worker(port: int, forge: Forgery, name: str = "rogue") -> Iterator[list[Ack]]:
    """The rogue in a thread until exit: the Acks its results got, in order."""
    acks: list[Ack] = []
    stop = threading.Event()
    session = zenoh.open(client_config(port))
    token = session.liveliness().declare_token(worker_key(name))

    def body() -> None:
        while not stop.is_set():
            request = encode(JobRequest(worker=name))
            answers = [r.ok for r in session.get(next_key(name), payload=request, timeout=WAIT)]
            if not answers or answers[0] is None:
                continue
            job = decode_next_reply(answers[0].payload.to_bytes())
            if isinstance(job, Idle):
                continue
            fitness, components, descriptors = evaluate_slice(
                job.config, job.key.generation, job.genomes
            )
            real = (fitness, components, descriptors)
            forged = forge(job.config, *real) if acks else real
            # honest once, so a result of it is accepted before it forges
            result = (
                Result(key=job.key, worker=name, start=job.start, stop=job.stop, error=forged)
                if isinstance(forged, str)
                else Result(
                    key=job.key,
                    worker=name,
                    start=job.start,
                    stop=job.stop,
                    fitness=forged[0][None],
                    components=forged[1][None],
                    descriptors=forged[2][None],
                )
            )
            replies = list(session.get(result_key(name), payload=encode(result), timeout=WAIT))
            if replies and replies[0].ok is not None:
                acks.append(decode_result_reply(replies[0].ok.payload.to_bytes())[0])

    thread = threading.Thread(target=body, name=f"rogue-{name}")
    thread.start()
    try:
        yield acks
    finally:
        stop.set()
        thread.join(WAIT)
        token.undeclare()  # type: ignore[no-untyped-call]
        session.close()  # type: ignore[no-untyped-call]
    assert not thread.is_alive()


@dataclass(frozen=True)
class RogueRun:
    """A run of CONFIG served beside the rogue and an honest worker, as the API then shows it."""

    run_id: int
    run: dict[str, Any]
    workers: dict[str, Any]
    metrics: str
    best: dict[str, Any]
    acks: list[Ack]


def rogue_run(tmp_path: Path, forge: Forgery, **settings: Any) -> RogueRun:
    """CONFIG on a real server with zenoh on loopback, the rogue forging with `forge` and an
    honest worker thread; parallel slices (the rogue gets jobs of every generation)."""
    zenoh_port = free_port()
    served = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zenoh_port}"],
        workers=0,
        jobs_per_worker=2,
        span_below_seconds=0.0,
        housekeeping_seconds=0.2,
        **settings,
    )
    with (
        serving(served) as (url, _app),
        httpx.Client(base_url=url, timeout=30) as client,
        rogue_worker(zenoh_port, forge) as acks,
        worker_thread(zenoh_port, "honest", evaluate_slice),
    ):
        assert eventually(lambda: len(client.get("/api/workers").json()) == 2, WAIT)
        run_id = client.post("/api/runs", json=CONFIG).json()["id"]
        run = wait_status(client, run_id, {"completed", "failed"})
        assert run["status"] == "completed", run["error"]
        return RogueRun(
            run_id,
            run,
            {w["name"]: w for w in client.get("/api/workers").json()},
            client.get("/metrics").text,
            client.get(f"/api/runs/{run_id}/best").json(),
            list(acks),
        )


def test_a_rogue_worker_is_quarantined_and_the_run_ends_as_an_honest_one(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    honest = evolve(RunConfig(**CONFIG))
    done = rogue_run(tmp_path, plausibly)
    assert Settings(db_url="unused").spot_checks == 1  # the default, which rogue_run keeps
    assert done.acks[0].accepted  # its honest result passed its spot-check
    assert not done.acks[1].accepted and "spot-check" in done.acks[1].reason
    rogue = done.workers["rogue"]
    assert rogue["quarantined"] is True
    reason = rogue["quarantine_reason"]
    assert (
        f"run {done.run_id} generation " in reason and "claimed " in reason
    )  # fitness or components
    assert done.workers["honest"]["quarantined"] is False
    warned = [r.getMessage() for r in caplog.records if r.name == "server.runs.scheduler"]
    assert len(warned) == 1 and "worker rogue quarantined" in warned[0] and reason in warned[0]
    assert "colony_workers_quarantined 1.0" in done.metrics
    assert "colony_spot_check_mismatches_total 1.0" in done.metrics
    assert done.best["sha256"] == honest.best.sha256
    assert done.run["best_fitness"] == honest.history[-1].best


@pytest.mark.parametrize(
    ("forge", "why"),
    [
        (beyond_physics, "is not Eq 12 of its components"),
        (nan_components, "must be finite"),
        (too_far, "the trial's reach at full speed"),
        (off_the_maze, "a descriptor outside [0, 1]"),
    ],
)
def test_claims_beyond_the_trials_physics_are_refused_without_a_spot_check(
    tmp_path: Path, forge: Forgery, why: str
) -> None:
    """Issue 38, attack 3: fitness values of 1.7e308 were stored as a generation's best and
    NaN components accepted, and descriptors off the maze were dropped as malformed, costing
    their credential nothing. With spot-checks off, such claims are still refused on arrival
    as forgeries, the rogue's credential is quarantined, and the run ends as an honest one."""
    honest = evolve(RunConfig(**CONFIG))
    done = rogue_run(tmp_path, forge, spot_checks=0)
    assert done.acks[0].accepted and not done.acks[1].accepted and why in done.acks[1].reason
    assert (
        done.workers["rogue"]["quarantined"] is True
        and why in done.workers["rogue"]["quarantine_reason"]
    )
    assert "colony_spot_check_mismatches_total 1.0" in done.metrics
    assert done.best["sha256"] == honest.best.sha256
    assert done.run["best_fitness"] == honest.history[-1].best


def test_a_workers_error_results_fail_no_run_and_repeated_ones_quarantine_it(
    tmp_path: Path,
) -> None:
    """Issue 38, attack 1: three error results from one credential failed a run. Now each job
    it erred on goes to the honest worker, the credential is quarantined at its third error in
    a row, and the run ends as an honest one."""
    honest = evolve(RunConfig(**CONFIG))
    done = rogue_run(tmp_path, lambda config, f, c, d: "RuntimeError: not today")
    assert done.acks[0].accepted
    assert [a.reason for a in done.acks[1:4]] == ["error recorded"] * 3
    rogue = done.workers["rogue"]
    assert rogue["quarantined"] is True
    assert "3 error results in a row" in rogue["quarantine_reason"]
    assert "RuntimeError: not today" in rogue["quarantine_reason"]
    assert done.workers["honest"]["quarantined"] is False
    assert "colony_workers_quarantined 1.0" in done.metrics
    assert "colony_spot_check_mismatches_total 0.0" in done.metrics
    assert done.run["error"] is None
    assert done.best["sha256"] == honest.best.sha256
    assert done.run["best_fitness"] == honest.history[-1].best
