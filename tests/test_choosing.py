"""A finished run's champion chosen by jobs (`server.runs.choosing`): after the last generation
the scheduler leases the candidates' validation, then the pick's held-out test, sliced per live
worker. Errors, departures, expired leases, quarantines, pauses and restarts change who scores
what and when, never the document: `champion`'s (`colony evolve`'s) bit for bit.

The scheduler as a state machine on a fake clock with the real science (fast at this size); the
run manager on real SQLite files; one real server with a real worker over zenoh."""

from __future__ import annotations

from pathlib import Path

import httpx
import numpy as np
import pytest
import sqlalchemy as sa
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.document import ControllerDocument
from evorobotics.evolution import RunLoop, evaluate_population
from evorobotics.ga import rank
from schemas.run import RunConfig, ValidationConfig
from schemas.wire import Job, Result, Stage
from server.core.db import make_engine, upgrade
from server.core.settings import Settings
from server.runs import crud
from server.runs.evaluation import run_job
from server.runs.lifecycle import RunManager
from server.runs.outbox import Written
from server.runs.policy import Policy
from server.runs.scheduler import Scheduler
from tests.helpers import (
    WAIT,
    drain,
    evaluated,
    eventually,
    evolved_champion,
    free_port,
    make_scheduler,
    reference,
    same_generations,
    serving,
    wait_status,
    worker_thread,
)

CONFIG = RunConfig(
    population=8,
    generations=2,
    trials=1,
    steps=5,
    job_size=3,
    seed=5,
    validation=ValidationConfig(poses=3, steps=30, candidates=5, test_poses=7),
)
RUN = 1
SLOW = 10.0
"""A speed at which a generation of CONFIG takes seconds: no spans."""
SETTINGS = Settings(db_url="unused", max_attempts=2, span_below_seconds=0.0)


def with_validation(config: RunConfig, poses: int, test_poses: int) -> RunConfig:
    v = config.validation.model_copy(update={"poses": poses, "test_poses": test_poses})
    return config.model_copy(update={"validation": v})


def lease_round(sched: Scheduler, names: list[str]) -> list[tuple[str, Job]]:
    """Each worker leases a job (none for some, when fewer are pending)."""
    return [(name, job) for name in names if (job := sched.lease(name)) is not None]


def settle_until(sched: Scheduler, names: list[str], stage: Stage) -> list[tuple[str, Job]]:
    """Settle every job honestly until the jobs leased are of `stage`; those, held."""
    while True:
        held = lease_round(sched, names)
        if not held or held[0][1].key.stage == stage:
            return held
        for name, job in held:
            assert sched.settle(run_job(job, name)).accepted


def finish(sched: Scheduler, names: list[str]) -> None:
    """Settle every job honestly until none is left."""
    while held := lease_round(sched, names):
        for name, job in held:
            assert sched.settle(run_job(job, name)).accepted


def forged(job: Job, worker: str) -> Result:
    """A careful forgery of a validate job: every candidate's mean Eq 12 one better, within
    anything a result's checks can tell."""
    honest = run_job(job, worker)
    assert honest.scores is not None
    scores = honest.scores.copy()
    scores[:, 0] += 1.0
    return honest.model_copy(update={"scores": scores})


def champion_of(written: list[Written]) -> ControllerDocument:
    assert written and written[-1].champion is not None
    return written[-1].champion


# the scheduler -------------------------------------------------------------------------------


def test_the_stages_are_jobs_after_the_last_generation_which_waits_for_its_champion() -> None:
    sched, _ = make_scheduler()
    names = ["a", "b"]
    for name in names:
        sched.join(name, speed=SLOW)
    sched.add(RUN, RunLoop(CONFIG), running=True)
    validate = settle_until(sched, names, "validate")
    told = sched.take_told()
    assert [(w.told.generation, w.last) for w in told] == [(0, False)]  # the last one waits
    last = reference(CONFIG, evaluate_population)[-1]
    order = rank(last.fitness)
    assert [(j.key.generation, j.start, j.stop) for _, j in validate] == [(1, 0, 3), (1, 3, 5)]
    for _, job in validate:
        assert job.span == 1 and job.state is None
        assert job.genomes.tobytes() == last.genomes[order[job.start : job.stop]].tobytes()
    assert sched.counts() == {"pending": 0, "leased": 2, "done": 0}
    for name, job in validate:
        assert sched.settle(run_job(job, name)).accepted
    test = lease_round(sched, names)
    assert [(j.key.stage, j.start, j.stop) for _, j in test] == [("test", 0, 4), ("test", 4, 7)]
    assert sched.take_told() == []
    for name, job in test:
        assert sched.settle(run_job(job, name)).accepted
    written = told + sched.take_told()
    same_generations(written, reference(CONFIG, evaluate_population))
    assert champion_of(written).to_json() == evolved_champion(CONFIG, RUN).to_json()
    assert not sched.has_pending() and sched.counts() == {"pending": 0, "leased": 0, "done": 0}
    assert sched.totals()["done"] == 2 + 2 + 2 + 2
    assert {w.name: w.evaluations for w in sched.workers()} == {"a": 8, "b": 8}  # training only


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    workers=st.integers(1, 4),
    per_worker=st.integers(1, 3),
    validation=st.sampled_from([(3, 7), (0, 7), (3, 0), (0, 0)]),
    data=st.data(),
)
def test_any_slicing_and_interleaving_chooses_champions_document(
    seed: int, workers: int, per_worker: int, validation: tuple[int, int], data: st.DataObject
) -> None:
    """Workers settle in any order, leave holding a job, or answer after their lease expired
    (so the live workers, and the slicing of the next stage, change; a lapsed job no live
    credential may take is the server's referee's): the written generations and the champion
    are `colony evolve`'s, bit for bit."""
    config = with_validation(CONFIG.model_copy(update={"seed": seed}), *validation)
    policy = Policy(jobs_per_worker=per_worker)
    sched, clock = make_scheduler(policy)
    names = [f"w{i}" for i in range(workers)]
    for name in names:
        sched.join(name, speed=SLOW)
    sched.add(RUN, RunLoop(config), running=True)
    written: list[Written] = []

    def store() -> bool:
        """The store keeps up; whether the run has ended."""
        told = sched.take_told()
        sched.written(told)
        written.extend(told)
        return bool(written) and written[-1].last

    for rounds in range(1000):
        if store():
            break
        held = lease_round(sched, names)
        if not held:  # the referee's: what lapsed with every live credential
            assert eventually(lambda: store() or sched.has_pending(), WAIT)
            continue
        for name, job in data.draw(st.permutations(held)):
            fate = data.draw(st.sampled_from(["settle", "leave", "late"])) if rounds < 20 else ""
            if fate == "leave":
                sched.leave(name)  # it comes back with its next request
            elif fate == "late":
                clock.t += policy.lease_max_s + 1
                sched.expire()
                assert not sched.settle(run_job(job, name)).accepted
            else:
                sched.settle(run_job(job, name))
    same_generations(written, reference(config, evaluate_population))
    assert champion_of(written).to_json() == evolved_champion(config, RUN).to_json()


def test_a_stage_job_that_errs_goes_to_another_credential_then_to_the_server() -> None:
    sched, _ = make_scheduler(Policy(max_attempts=2))
    names = ["a", "b"]
    for name in names:
        sched.join(name, speed=SLOW)
    sched.add(RUN, RunLoop(CONFIG), running=True)
    (_, first), (_, second) = settle_until(sched, names, "validate")
    assert sched.settle(run_job(second, "b")).accepted
    failed = Result(key=first.key, worker="a", start=first.start, stop=first.stop, error="boom")
    assert sched.settle(failed).reason == "error recorded"
    assert sched.lease("a") is None  # it erred on the only job pending
    again = sched.lease("b")
    assert again is not None and again.key == first.key
    failed = failed.model_copy(update={"worker": "b"})
    assert sched.settle(failed).reason == "error recorded"  # two credentials: the server's
    assert eventually(lambda: sched.counts()["pending"] == 2, WAIT)  # the test's jobs
    finish(sched, names)
    written = sched.take_told()
    assert champion_of(written).to_json() == evolved_champion(CONFIG, RUN).to_json()
    assert sched.quarantined() == {} and sched.take_failed() == {}
    sched.close()


def test_a_stage_job_the_server_cannot_score_fails_the_run(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Only the server's own scoring failing fails a run (its physics broken here by hand)."""

    def broken(*args: object) -> np.ndarray:
        raise RuntimeError("simulated scoring crash")

    monkeypatch.setattr("server.runs.evaluation.stage_scores", broken)
    sched, _ = make_scheduler(Policy(max_attempts=1))
    sched.join("a", speed=SLOW)
    sched.add(RUN, RunLoop(CONFIG), running=True)
    ((_, job),) = settle_until(sched, ["a"], "validate")
    failed = Result(key=job.key, worker="a", start=job.start, stop=job.stop, error="boom")
    assert sched.settle(failed).accepted
    failed_runs: dict[int, str] = {}
    assert eventually(lambda: bool(failed_runs.update(sched.take_failed()) or failed_runs), WAIT)
    assert "simulated scoring crash" in failed_runs[RUN]
    assert not sched.has_pending() and sched.counts() == {"pending": 0, "leased": 0, "done": 0}
    sched.close()


def test_a_quarantine_during_a_stage_returns_the_credentials_accepted_rows_to_pending() -> None:
    """Spot-checks score again every row of a stage's result (`spot_checks` at least its
    rows): an honest result passes; a forged one quarantines its credential, and the rows it
    scored before are scored again by others."""
    sched, _ = make_scheduler(Policy(jobs_per_worker=2, spot_checks=10))
    names = ["honest", "cheat"]
    for name in names:
        sched.join(name, speed=SLOW)
    sched.add(RUN, RunLoop(CONFIG), running=True)
    held = dict(settle_until(sched, names, "validate"))
    assert [(j.start, j.stop) for j in held.values()] == [(0, 2), (2, 4)]
    checked = sched.spot_totals()["results_checked"]
    for name, job in held.items():
        assert sched.settle(run_job(job, name)).accepted
    assert sched.spot_totals()["results_checked"] == checked + 2
    assert sched.counts() == {"pending": 1, "leased": 0, "done": 2}
    last = sched.lease("cheat")
    assert last is not None and (last.start, last.stop) == (4, 5)
    ack = sched.settle(forged(last, "cheat"))
    assert not ack.accepted and "quarantined" in (ack.reason or "")
    assert "cheat" in sched.quarantined() and "validate row 4" in sched.quarantined()["cheat"]
    assert sched.counts() == {"pending": 2, "leased": 0, "done": 1}  # its rows 2:4 too
    assert sched.lease("cheat") is None
    finish(sched, names)
    written = sched.take_told()
    assert champion_of(written).to_json() == evolved_champion(CONFIG, RUN).to_json()


def test_a_paused_run_leases_no_stage_job_and_a_forgotten_one_drops_their_results() -> None:
    sched, _ = make_scheduler()
    names = ["a", "b"]
    for name in names:
        sched.join(name, speed=SLOW)
    sched.add(RUN, RunLoop(CONFIG), running=True)
    (_, first), _ = settle_until(sched, names, "validate")
    sched.set_running(RUN, False)
    assert sched.settle(run_job(first, "a")).accepted  # leased before the pause: it counts
    sched.leave("b")  # its job returns to pending, and waits for the resume
    assert sched.lease("a") is None and not sched.has_pending()
    sched.set_running(RUN, True)
    finish(sched, names)
    assert champion_of(sched.take_told()).to_json() == evolved_champion(CONFIG, RUN).to_json()

    sched.add(2, RunLoop(CONFIG), running=True)
    (_, job), *_ = settle_until(sched, names, "test")
    sched.forget(2)
    assert sched.settle(run_job(job, "a")).reason == "no lease held: late or duplicate"
    assert all(not w.last for w in sched.take_told())


# the run manager -----------------------------------------------------------------------------


def engine_in(tmp_path: Path) -> sa.Engine:
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    return engine


def to_stage(manager: RunManager, stage: Stage) -> Job:
    """Evaluate, settle and write jobs until one of `stage` is leased (to "w"); it, held."""
    while True:
        job = manager.scheduler.lease("w")
        assert job is not None
        if job.key.stage == stage:
            return job
        assert manager.scheduler.settle(run_job(job, "w")).accepted
        manager.flush()


def stored_run(manager: RunManager, run_id: int) -> tuple[str, int, str | None]:
    with manager.sessions() as session:
        run = crud.find_run(session, run_id=run_id)
        return run.status, run.generation, run.champion_sha256


def test_a_server_restarted_while_choosing_redoes_the_last_generation(tmp_path: Path) -> None:
    engine = engine_in(tmp_path)
    manager = RunManager(engine, SETTINGS)
    run_id = manager.create_run(CONFIG)
    to_stage(manager, "test")
    assert stored_run(manager, run_id) == ("running", 1, None)  # the last generation waits
    restarted = RunManager(engine, SETTINGS)  # the first one died with its stage in hand
    restarted.recover()
    job = restarted.scheduler.lease("w")
    assert job is not None and (job.key.generation, job.key.stage) == (1, "train")
    restarted.scheduler.settle(run_job(job, "w"))
    drain(restarted)
    assert stored_run(restarted, run_id)[0] == "completed"
    assert restarted.best(run_id).to_json() == evolved_champion(CONFIG, run_id).to_json()
    engine.dispose()


def test_pause_resume_and_cancel_during_the_champions_stages(tmp_path: Path) -> None:
    engine = engine_in(tmp_path)
    manager = RunManager(engine, SETTINGS)
    paused, cancelled = manager.create_run(CONFIG), manager.create_run(CONFIG)
    job = to_stage(manager, "validate")
    assert job.key.run_id == paused
    manager.pause(paused)
    assert manager.scheduler.settle(run_job(job, "w")).accepted  # leased before: it counts
    to_stage(manager, "validate")  # the other run's
    manager.cancel(cancelled)
    assert evaluated(manager, "w") is None  # nothing leasable: one paused, one cancelled
    manager.resume(paused)
    drain(manager)
    assert stored_run(manager, paused)[0] == "completed"
    assert manager.best(paused).to_json() == evolved_champion(CONFIG, paused).to_json()
    assert stored_run(manager, cancelled) == ("cancelled", 1, None)
    engine.dispose()


@pytest.mark.parametrize("status", ["running", "paused", "failed", "completed"])
def test_a_last_generation_stored_without_its_champion_gets_it_from_jobs(
    tmp_path: Path, status: str
) -> None:
    """An older server wrote a run's last generation before choosing its champion: the
    champion's stages are served from the stored generation (a live run completes with it; a
    failed one once resumed; a completed one has it named), nothing evaluated again."""
    engine = engine_in(tmp_path)
    manager = RunManager(engine, SETTINGS)
    run_id = manager.create_run(CONFIG)
    drain(manager)
    expected = evolved_champion(CONFIG, run_id)
    with manager.sessions.begin() as session:
        run = crud.find_run(session, run_id=run_id)
        assert run.champion_sha256 == expected.sha256
        run.status, run.champion_sha256 = status, None
        row = crud.get_controller(session, sha256=expected.sha256)
        assert row is not None
        session.delete(row)
    restarted = RunManager(engine, SETTINGS)
    restarted.recover()
    if status == "paused":
        assert evaluated(restarted, "w") is None
        restarted.resume(run_id)
    if status == "failed":
        restarted.resume(run_id)  # queued, then running: its champion's stages
    job = restarted.scheduler.lease("w")
    assert job is not None and job.key.stage == "validate"
    assert restarted.scheduler.settle(run_job(job, "w")).accepted
    drain(restarted)
    assert stored_run(restarted, run_id) == ("completed", 2, expected.sha256)
    assert restarted.best(run_id).to_json() == expected.to_json()
    with restarted.sessions() as session:
        stored = crud.get_controller(session, sha256=expected.sha256)
        assert stored is not None and stored.document == expected.to_json()
        assert len(crud.list_generations(session, run_id=run_id)) == 2
    engine.dispose()


# a real server and a real worker -------------------------------------------------------------


def test_a_server_with_a_worker_stores_colony_evolves_champion(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker scores the champion's stages: the server's own scoring is broken here, so
    the run would fail had the server scored any (spot-checks off)."""
    from worker.main import evaluate_slice

    def broken(*args: object) -> np.ndarray:
        raise RuntimeError("the server scored a stage")

    monkeypatch.setattr("server.runs.evaluation.stage_scores", broken)
    zport = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        workers=0,
        spot_checks=0,
    )
    with (
        serving(settings) as (url, app),
        httpx.Client(base_url=url, timeout=30) as client,
        worker_thread(zport, "worker", evaluate_slice) as stats,
    ):
        created = client.post("/api/runs", json=CONFIG.model_dump(mode="json"))
        run_id = created.json()["id"]
        run = wait_status(client, run_id, {"completed", "failed"})
        assert run["status"] == "completed", run["error"]
        best = client.get(f"/api/runs/{run_id}/best").json()
        totals = app.state.manager.scheduler.totals()
    assert best == evolved_champion(CONFIG, run_id).to_dict()
    assert stats.jobs_done >= CONFIG.generations + 2 and totals["done"] == stats.jobs_done


def test_a_server_without_workers_stores_colony_evolves_champion(tmp_path: Path) -> None:
    """No zenoh: the in-process executor's threads take the stage jobs."""
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}", port=free_port(), executors=2, zenoh=False
    )
    with serving(settings) as (url, _), httpx.Client(base_url=url, timeout=30) as client:
        run_id = client.post("/api/runs", json=CONFIG.model_dump(mode="json")).json()["id"]
        run = wait_status(client, run_id, {"completed", "failed"})
        assert run["status"] == "completed", run["error"]
        best = client.get(f"/api/runs/{run_id}/best").json()
    assert best == evolved_champion(CONFIG, run_id).to_dict()
