"""A rogue worker returning forged fitness cannot win a run: claims beyond the trial's physics
are refused on arrival, plausible ones are caught by the server's spot-checks.

A real server (uvicorn, SQLite in a temp dir, its zenoh router on a loopback port), an honest
worker thread evaluating for real, and a rogue: a plain zenoh client speaking the wire
protocol that answers its first job honestly, then forges every result after.
"""

from __future__ import annotations

import math
import queue
import threading
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh

from evorobotics.document import ControllerDocument
from evorobotics.evaluate import evaluate, implausible, trial_steps
from evorobotics.evolution import evolve
from evorobotics.fitness import mean_fitness
from evorobotics.maze import load_maze
from evorobotics.reports import stage_scores
from schemas.robots import (
    ControllerPush,
    PushAck,
    Replacement,
    StuckRequest,
    ack_key,
    alive_key,
    command_key,
    decode_message,
    encode_message,
    replace_key,
)
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
from server.runs import crud
from tests.helpers import (
    WAIT,
    client_config,
    constant_drive,
    eventually,
    free_port,
    plausible_forgery,
    serving,
    wait_status,
    worker_thread,
    zenoh_client,
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


def crowned(config: RunConfig, f: np.ndarray, c: np.ndarray, d: np.ndarray) -> Claims:
    """The slice's first individual claims the most any trial allows (`crown`), with Eq 12 of
    that as its fitness: within physics, false, and fitter than any honest claim."""
    c = c.copy()
    c[0] = crown(config)
    f = f.copy()
    f[0] = mean_fitness(c[:1], config.fitness)[0]
    assert implausible(config, f, c, d) is None
    return f, c, d


def crown(config: RunConfig) -> np.ndarray:
    """(4,) Eq 12 components no trial of `config` can beat: a curve at full speed all along
    (the fastest wheel gain its gap allows), offsets of that reach or the maze's diagonal,
    never stuck."""
    world, maze = config.world, load_maze(config.maze)
    fastest = max(world.motor_gain) * (1.0 + world.gap_motor_gain)
    reach = trial_steps(config) * world.dt * world.max_speed * fastest
    offset = min(reach, math.hypot(maze.width, maze.height))
    return np.array([reach, offset, offset, 0.0])


def crown_fitness(config: RunConfig) -> float:
    """The fitness `crowned` claims."""
    return float(mean_fitness(np.tile(crown(config), (1, config.trials, 1)), config.fitness)[0])


@contextmanager
def rogue_worker(
    port: int, forge: Forgery, name: str = "rogue", until: int | None = None
) -> Iterator[list[Ack]]:
    """The rogue in a thread until exit: the Acks its results got, in order. With `until`,
    it takes a job of a later generation and then falls silent, holding it: the run stays
    running with `until` its latest committed generation."""
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
            if until is not None and job.key.generation > until:
                return
            if job.key.stage != "train":  # a champion's stage or a report: scored honestly
                scores = stage_scores(
                    job.config, job.key.stage, job.genomes, job.start, job.stop, job.report
                )
                stage = Result(
                    key=job.key, worker=name, start=job.start, stop=job.stop, scores=scores
                )
                list(session.get(result_key(name), payload=encode(stage), timeout=WAIT))
                continue
            fitness, components, descriptors = evaluate_slice(
                job.config, job.key.generation, job.evaluated()
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
                    checks=len(fitness) - (job.stop - job.start),
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


def crowning_server(tmp_path: Path, zenoh_port: int, **settings: Any) -> Settings:
    """A server on loopback whose only worker will be a crowning rogue, never spot-checked (so
    its forgeries are told), without spans (the rogue evaluates one generation per job)."""
    return Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zenoh_port}"],
        workers=0,
        span_below_seconds=0.0,
        housekeeping_seconds=0.2,
        spot_checks=0,
        **settings,
    )


@contextmanager
def plain_robot(session: zenoh.Session, robot: str) -> Iterator[queue.SimpleQueue[ControllerPush]]:
    """`robot` online as a bare zenoh client: the pushes it is sent, in order."""
    pushes: queue.SimpleQueue[ControllerPush] = queue.SimpleQueue()

    def on_command(sample: zenoh.Sample) -> None:
        message = decode_message(sample.payload.to_bytes())
        if isinstance(message, ControllerPush):
            pushes.put(message)

    subscriber = session.declare_subscriber(command_key(robot), on_command)
    token = session.liveliness().declare_token(alive_key(robot))
    try:
        yield pushes
    finally:
        token.undeclare()  # type: ignore[no-untyped-call]
        subscriber.undeclare()  # type: ignore[no-untyped-call]


def test_a_genome_crowned_by_forged_fitness_is_neither_a_running_runs_best_nor_pushed(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 38: a worker credential claiming the most physics allows for one genome of each
    result (plausible, so only a spot-check could catch it, and they are off) made it training
    rank 0, which a running run's best and a push of the run served. The server now serves
    the best rank whose claimed fitness its own evaluation repeats bit for bit."""
    config = RunConfig(**CONFIG)
    zenoh_port = free_port()
    with (
        serving(crowning_server(tmp_path, zenoh_port)) as (url, _app),
        httpx.Client(base_url=url, timeout=30) as client,
        rogue_worker(zenoh_port, crowned, until=1),
        zenoh_client(zenoh_port) as session,
        plain_robot(session, "r-crown") as pushes,
    ):
        run_id = client.post("/api/runs", json=CONFIG).json()["id"]
        assert eventually(lambda: client.get(f"/api/runs/{run_id}").json()["generation"] == 2)
        assert client.get(f"/api/runs/{run_id}").json()["status"] == "running"
        ranked = client.get(f"/api/runs/{run_id}/individuals").json()
        assert ranked["generation"] == 1
        fitness = [i["fitness"] for i in ranked["individuals"]]
        assert fitness[0] == crown_fitness(config)  # the forgery was told: rank 0 as claimed
        honest = next(k for k, f in enumerate(fitness) if f != fitness[0])

        best = ControllerDocument.from_json(client.get(f"/api/runs/{run_id}/best").text)
        assert best.sha256 == ranked["individuals"][honest]["sha256"]
        assert best.provenance["rank"] == honest and best.fitness == fitness[honest]
        assert evaluate(config, 1, best.weights[None]).fitness[0] == best.fitness

        assert eventually(lambda: client.get("/api/robots/r-crown").status_code == 200, WAIT)
        with ThreadPoolExecutor(1) as pool:
            reply = pool.submit(
                client.post, "/api/robots/r-crown/controller", json={"run_id": run_id}
            )
            push = pushes.get(timeout=WAIT)
            ack = PushAck(robot="r-crown", push_id=push.push_id, accepted=True, sha256=push.sha256)
            session.put(ack_key("r-crown"), encode_message(ack))
            assert reply.result(WAIT).json()["accepted"]
        assert push.sha256 == best.sha256
        rank0 = client.post("/api/robots/r-crown/controller", json={"run_id": run_id, "rank": 0})
        assert rank0.status_code == 409 and "rank 0's claimed fitness is not" in rank0.text
        assert pushes.empty()
    skipped = [r.getMessage() for r in caplog.records if r.name == "server.runs.champions"]
    assert skipped and all("rank 0: claimed fitness" in m for m in skipped)


def test_the_archive_policy_never_serves_an_elite_crowned_by_forged_fitness(
    tmp_path: Path,
) -> None:
    """Issue 38: a robot stuck with a controller of a map-elites run that is not in its
    archive got the elite of highest claimed fitness, one a crowning rogue chose. The server
    now serves the fittest elite whose archived claim its own evaluation repeats, and refuses
    to push an elite whose claim it does not."""
    config = {**CONFIG, "strategy": "map-elites", "generations": 3}
    zenoh_port = free_port()
    with (
        serving(crowning_server(tmp_path, zenoh_port, replacement="archive")) as (url, app),
        httpx.Client(base_url=url, timeout=30) as client,
        rogue_worker(zenoh_port, crowned),
        zenoh_client(zenoh_port) as session,
    ):
        run_id = client.post("/api/runs", json=config).json()["id"]
        run = wait_status(client, run_id, {"completed", "failed"})
        assert run["status"] == "completed", run["error"]
        cells = client.get(f"/api/runs/{run_id}/archive").json()["cells"]
        by_fitness = sorted(cells, key=lambda cell: -cell["fitness"])  # stable, as served
        crown = crown_fitness(RunConfig(**config))
        assert by_fitness[0]["fitness"] == crown  # the fittest elite as claimed: a forgery
        expected = next(cell["sha256"] for cell in by_fitness if cell["fitness"] != crown)

        wall = constant_drive(0.87, 0.87, RunConfig(**config).network_spec)  # not an elite
        with app.state.manager.sessions.begin() as db:
            crud.put_controller(
                db, sha256=wall.sha256, document=wall.to_json(), run_id=run_id,
                generation=None, fitness=None,
            )  # fmt: skip
        request = StuckRequest(
            robot="r-stuck", sha256=wall.sha256, reason="test", step=1, nonce=uuid.uuid4().hex
        )
        replies = list(session.get(replace_key("r-stuck"), payload=encode_message(request)))
        assert len(replies) == 1 and replies[0].ok is not None
        answer = decode_message(replies[0].ok.payload.to_bytes())
        forged = next(k for k, cell in enumerate(cells) if cell["fitness"] == crown)
        pushed = client.post(
            "/api/robots/r-stuck/controller", json={"run_id": run_id, "elite": forged}
        )
        assert pushed.status_code == 409 and f"elite {forged}: its archived fitness" in pushed.text
    assert isinstance(answer, Replacement) and answer.document is not None, answer
    assert ControllerDocument.from_json(answer.document).sha256 == expected
    assert "fittest (the stuck controller is not in it)" in answer.reason
