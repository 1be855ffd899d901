"""A controller's reports as jobs (`evorobotics.reports`, `Scheduler.report`): the trials of an
exploration report or a robustness map, cut into any slices and simulated anywhere, assemble to
what `explore` and `robustness` compute in one process, bit for bit; the scheduler leases them
before runs' jobs, retries, referees and spot-checks them like a champion's stage, and refuses
rows no trial can give. A study's exploration figures through a real server: the same with a
real worker taking the jobs (the server's own scoring broken) and with no worker.

The science at small sizes; the scheduler as a state machine on a fake clock; real uvicorn, real
zenoh on loopback and SQLite in temp dirs for the study."""

from __future__ import annotations

import itertools
import json
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.document import ControllerDocument
from evorobotics.evolution import RunLoop
from evorobotics.explore import TRIAL_COLUMNS, explore
from evorobotics.reports import Report, assemble, stage_scores
from evorobotics.robustness import CELLS, robustness
from schemas.run import RunConfig, ValidationConfig
from schemas.wire import (
    EXPLORE_COLUMNS,
    MAP_CELLS,
    Job,
    JobKey,
    ReportSpec,
    ReportStage,
    Result,
    decode,
    encode,
    report_config,
)
from schemas.world import World
from server.core.settings import Settings
from server.runs.evaluation import run_job
from server.runs.policy import Policy
from server.runs.scheduler import Scheduler
from tests.helpers import (
    REACTIVE,
    WAIT,
    constant_drive,
    eventually,
    free_port,
    make_scheduler,
    random_controller,
    serving,
    worker_thread,
)

SLOW = 10.0
"""A worker speed at which no generation is a span."""
ROAMER = constant_drive(0.9, 0.6)
"""Drives in circles: confined, then stuck, or roaming, depending on the start pose."""
SPEC = ReportSpec(poses=9, steps=130)
MAP = ReportSpec(poses=2, steps=60)
STUDY: dict[str, Any] = {
    "population": 6,
    "generations": 2,
    "steps": 5,
    "trials": 1,
    "job_size": 2,
    "validation": {"poses": 3, "steps": 40, "candidates": 2, "test_poses": 5},
}
"""Runs of a second whose champions' exploration (1000 poses x 1000 steps) is most of a
study's simulation."""


def config_of(doc: ControllerDocument, maze: str = "paper", seed: int = 0) -> RunConfig:
    return report_config(doc.spec, doc.world or World(), maze, seed)


def same_bits(a: Report, b: Report) -> bool:
    """Every figure, bit for bit (a float's JSON is its shortest exact repr)."""
    return json.dumps(a.as_dict(), sort_keys=True) == json.dumps(b.as_dict(), sort_keys=True)


def whole(stage: ReportStage, doc: ControllerDocument, spec: ReportSpec, **kw: Any) -> Report:
    """`colony evaluate`'s report of `doc`, computed in one process."""
    if stage == "robustness":
        return robustness(doc.spec, doc.weights, poses=spec.poses, steps=spec.steps, **kw)
    gap = spec.reality_gap
    return explore(doc.spec, doc.weights, poses=spec.poses, steps=spec.steps, reality_gap=gap, **kw)


def in_slices(
    stage: ReportStage, config: RunConfig, spec: ReportSpec, weights: np.ndarray, cuts: list[int]
) -> Report:
    """The report from its trials cut at `cuts`, each slice simulated on its own."""
    n = spec.poses if stage == "explore" else CELLS * spec.poses
    bounds = [0, *sorted(c for c in set(cuts) if 0 < c < n), n]
    rows = [
        stage_scores(config, stage, weights[None], a, b, spec)
        for a, b in itertools.pairwise(bounds)
    ]
    return assemble(config, stage, spec, np.concatenate(rows))


def settle_all(sched: Scheduler, names: list[str]) -> None:
    """Every worker leases and settles honestly until nothing is left."""
    while held := [(n, j) for n in names if (j := sched.lease(n)) is not None]:
        for name, job in held:
            assert sched.settle(run_job(job, name)).accepted


def explored(sched: Scheduler, doc: ControllerDocument, spec: ReportSpec = SPEC) -> Future[Report]:
    return sched.report("explore", config_of(doc), spec, doc.weights)


# the science ----------------------------------------------------------------------------------


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 3),
    report_seed=st.integers(0, 2**20),
    steps=st.sampled_from([25, 40, 130]),
    gap=st.sampled_from(["none", "trial", "step"]),
    cuts=st.lists(st.integers(1, 8), max_size=8),
)
def test_an_exploration_in_any_slices_is_explores_bit_for_bit(
    seed: int, report_seed: int, steps: int, gap: str, cuts: list[int]
) -> None:
    doc = random_controller(seed) if seed else ROAMER
    world = World(gap_model="step") if gap == "step" else World()
    spec = ReportSpec(poses=9, steps=steps, reality_gap=gap != "none")
    config = report_config(doc.spec, world, "paper", report_seed)
    got = in_slices("explore", config, spec, doc.weights, cuts)
    want = whole("explore", doc, spec, seed=report_seed, world=world)
    assert same_bits(got, want)


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 3), cuts=st.lists(st.integers(1, 2 * MAP_CELLS - 1), max_size=6))
def test_a_robustness_map_in_any_slices_is_robustness_bit_for_bit(
    seed: int, cuts: list[int]
) -> None:
    doc = random_controller(seed) if seed else ROAMER
    got = in_slices("robustness", config_of(doc, "arena", 3), MAP, doc.weights, cuts)
    want = whole("robustness", doc, MAP, maze="arena", seed=3, threads=2)
    assert CELLS == MAP_CELLS and same_bits(got, want)


def test_a_report_jobs_wire_checks_its_slice_and_its_rows() -> None:
    config, genome = config_of(ROAMER), ROAMER.weights[None]
    key = JobKey(run_id=7, generation=0, index=0, stage="robustness")
    job = Job(key=key, start=97, stop=98, config=config, genomes=genome, report=MAP)
    assert decode(encode(job), Job).report == MAP and key.label() == "report 7 robustness job 0"
    bads: list[tuple[dict[str, Any], str]] = [
        ({"stop": 99}, "outside 98"),
        ({"report": None}, "only a report's"),
        ({"report": MAP.model_copy(update={"reality_gap": True})}, "sets the gap per cell"),
        ({"genomes": np.zeros((2, REACTIVE.weight_count))}, "expected float64"),
        ({"key": key.model_copy(update={"generation": 1})}, "generation 0"),
    ]
    for bad, why in bads:
        with pytest.raises(ValueError, match=why):
            Job.model_validate({**job.model_dump(), **bad})
    with pytest.raises(ValueError, match="only a report's"):
        Job(key=key.model_copy(update={"stage": "test"}), start=0, stop=1, config=config,
            genomes=genome, report=MAP)  # fmt: skip
    rows = stage_scores(config, "explore", genome, 0, 3, SPEC)
    assert rows.shape == (3, EXPLORE_COLUMNS) == (3, len(TRIAL_COLUMNS))
    explore_key = key.model_copy(update={"stage": "explore"})
    honest = Result(key=explore_key, worker="w", start=0, stop=3, scores=rows)
    assert decode(encode(honest), Result).scores is not None
    for column, value, why in [
        (0, 0.0, "stuck step"),
        (0, 2.5, "stuck step"),
        (1, 0.5, "confined"),
        (6, 1e3, "offsets"),
        (5, -1.0, "curve length"),
        (4, 0.0, "whole number of cells"),
    ]:
        forged = rows.copy()
        forged[1, column] = value
        with pytest.raises(ValueError, match=why):
            Result.model_validate({**honest.model_dump(), "scores": forged})
    with pytest.raises(ValueError, match="not both"):
        Result(key=key, worker="w", start=0, stop=1, scores=np.array([[1.0, 1.0]]))


# the scheduler --------------------------------------------------------------------------------


def test_a_report_is_cut_per_worker_leased_before_runs_and_assembled_bit_for_bit() -> None:
    sched, _ = make_scheduler()
    names = ["a", "b", "c", "d"]
    for name in names:
        sched.join(name, speed=SLOW)
    run = RunConfig(
        population=8,
        generations=2,
        trials=1,
        steps=5,
        job_size=2,
        validation=ValidationConfig(poses=0, test_poses=0),
    )
    sched.add(1, RunLoop(run), running=True)
    future = explored(sched, ROAMER)
    assert explored(sched, ROAMER) is future  # asked again while in flight: the same report
    jobs = [j for name in names if (j := sched.lease(name)) is not None]
    assert [(j.key.stage, j.start, j.stop) for j in jobs[:3]] == [
        ("explore", 0, 3),
        ("explore", 3, 6),
        ("explore", 6, 9),
    ]
    assert jobs[3].key.stage == "train"  # the run's jobs wait for the report's
    assert all(j.report == SPEC and j.key.report for j in jobs[:3])
    for job, name in zip(jobs, names, strict=True):
        assert sched.settle(run_job(job, name)).accepted
    assert future.done() and same_bits(future.result(), whole("explore", ROAMER, SPEC))
    settle_all(sched, names)  # the run goes on, its last generation to the store
    assert [w.told.generation for w in sched.take_told()] == [0, 1]
    again = explored(sched, ROAMER)  # done and dropped: asked again, it is computed again
    assert again is not future and not again.done()
    sched.close()
    with pytest.raises(RuntimeError, match="stopping"):
        again.result(0)


def test_a_bad_report_is_refused_before_any_job() -> None:
    sched, _ = make_scheduler()
    sched.join("a", speed=SLOW)
    config, weights = config_of(ROAMER), ROAMER.weights
    with pytest.raises(ValueError, match="maze"):
        sched.report("explore", config.model_copy(update={"maze": "nowhere"}), SPEC, weights)
    with pytest.raises(ValueError, match="limit of 20000000 robot steps"):
        sched.report("robustness", config, ReportSpec(poses=300, steps=2000), weights)
    with pytest.raises(ValueError, match="weights for a network"):
        sched.report("explore", config, SPEC, weights[:-1])
    assert not sched.has_pending() and sched.lease("a") is None
    sched.close()


def test_a_report_job_that_errs_goes_to_another_credential_then_to_the_server() -> None:
    sched, _ = make_scheduler(Policy(max_attempts=2))
    for name in ("a", "b"):
        sched.join(name, speed=SLOW)
    future = sched.report("robustness", config_of(ROAMER), MAP, ROAMER.weights)
    first = sched.lease("a")
    assert first is not None and first.key.stage == "robustness"
    for name in ("a", "b"):
        erred = Result(key=first.key, worker=name, start=first.start, stop=first.stop, error="x")
        assert sched.settle(erred).reason == "error recorded"
        if name == "a":
            again = sched.lease("b")
            assert again is not None and (again.key, again.start) == (first.key, first.start)
    assert eventually(lambda: sched.counts()["done"] == 1, WAIT)  # the server's own
    settle_all(sched, ["a", "b"])
    assert future.result(WAIT) and same_bits(future.result(), whole("robustness", ROAMER, MAP))
    assert sched.quarantined() == {} and sched.take_failed() == {}
    sched.close()


def test_rows_beyond_a_trials_physics_or_a_spot_check_quarantine_and_return_to_pending() -> None:
    sched, _ = make_scheduler(Policy(jobs_per_worker=2, spot_checks=10))
    names = ["honest", "cheat", "liar"]
    for name in names:
        sched.join(name, speed=SLOW)
    future = explored(sched, ROAMER, ReportSpec(poses=12, steps=130))
    held = {name: sched.lease(name) for name in names}
    honest = held["honest"]
    assert honest is not None and sched.settle(run_job(honest, "honest")).accepted
    cheat, liar = held["cheat"], held["liar"]
    assert cheat is not None and liar is not None
    true = run_job(cheat, "cheat")
    assert true.scores is not None
    plausible = true.scores.copy()
    plausible[:, 4] += 1.0  # a cell more each: only a re-run tells
    ack = sched.settle(true.model_copy(update={"scores": plausible}))
    assert not ack.accepted and "explore row" in sched.quarantined()["cheat"]
    lie = run_job(liar, "liar")
    assert lie.scores is not None
    beyond = lie.scores.copy()
    beyond[0, 0] = 131.0  # stuck after the report's last step
    ack = sched.settle(lie.model_copy(update={"scores": beyond}))
    assert not ack.accepted and "beyond the report's 130 steps" in sched.quarantined()["liar"]
    settle_all(sched, names)
    assert same_bits(future.result(WAIT), whole("explore", ROAMER, ReportSpec(poses=12, steps=130)))
    sched.close()


@pytest.mark.parametrize("stage", ["rank", "robustness"])
def test_a_result_keyed_to_another_stage_is_dropped_unread(stage: str) -> None:
    """A worker holding an exploration's job answers as if it were a ranking's or a map's
    (fewer columns, valid on the wire): no job of that report, acknowledged as dropped."""
    sched, _ = make_scheduler()
    sched.join("w", speed=SLOW)
    future = sched.report("explore", config_of(ROAMER), SPEC, ROAMER.weights)
    job = sched.lease("w")
    assert job is not None and job.key.stage == "explore"
    columns = 3 if stage == "rank" else 2
    other = Result(
        key=job.key.model_copy(update={"stage": stage}),
        worker="w",
        start=job.start,
        stop=job.stop,
        scores=np.zeros((job.stop - job.start, columns)),
    )
    ack = sched.settle(decode(encode(other), Result))
    assert not ack.accepted and "no lease held" in ack.reason
    assert sched.quarantined() == {} and not future.done()
    assert sched.settle(run_job(job, "w")).accepted  # its own result still counts
    sched.close()


def test_the_servers_own_evaluation_failing_fails_the_report_and_no_run(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def broken(*args: object) -> np.ndarray:
        raise RuntimeError("simulated scoring crash")

    monkeypatch.setattr("server.runs.evaluation.stage_scores", broken)
    sched, _ = make_scheduler()
    sched.join("local-0", listed=False)  # an in-process executor: the server's own
    future = explored(sched, ROAMER)
    job = sched.lease("local-0")
    assert job is not None
    assert sched.settle(run_job(job, "local-0")).accepted
    with pytest.raises(RuntimeError, match="simulated scoring crash"):
        future.result(0)
    assert sched.take_failed() == {} and not sched.has_pending()
    sched.close()


# a real server --------------------------------------------------------------------------------


def study_figures(url: str) -> list[tuple[ControllerDocument, dict[str, Any]]]:
    """A two-run study of STUDY to the end: each champion with its run's metrics."""
    body = {"name": "explored", "base": STUDY, "seeds": [1, 2]}
    with httpx.Client(base_url=url, timeout=60) as client:
        created = client.post("/api/studies", json=body)
        assert created.status_code == 201, created.text
        study_id = created.json()["id"]

        def explored() -> bool:
            runs = client.get(f"/api/studies/{study_id}").json()["runs"]
            return all(r["metrics"]["coverage"] is not None for r in runs)

        assert eventually(explored, 180)
        runs = client.get(f"/api/studies/{study_id}").json()["runs"]
        return [
            (
                ControllerDocument.from_json(client.get(f"/api/runs/{r['run_id']}/best").content),
                r["metrics"],
            )
            for r in runs
        ]


def check_explored(figures: list[tuple[ControllerDocument, dict[str, Any]]]) -> None:
    """Each run's exploration figures are `colony evaluate`'s of its champion, bit for bit."""
    for doc, metrics in figures:
        want = explore(doc.spec, doc.weights, world=doc.world)
        got = [metrics[k] for k in ("roaming", "stuck", "max_offset", "coverage")]
        assert got == [want.roaming, want.stuck[1000], want.max_offset[1000], want.coverage]


def test_a_studys_exploration_is_the_workers_and_colony_evaluates(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server's own scoring is broken: had it simulated any report (or stage), the study
    would never show its figures."""
    from worker.main import evaluate_slice

    def broken(*args: object) -> np.ndarray:
        raise RuntimeError("the server simulated a report")

    monkeypatch.setattr("server.runs.evaluation.stage_scores", broken)
    zport = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        workers=0,
        spot_checks=0,
    )
    with serving(settings) as (url, _), worker_thread(zport, "worker", evaluate_slice):
        figures = study_figures(url)
        sha = figures[0][0].sha256
        mapped = httpx.get(f"{url}/api/controllers/{sha}/robustness?poses=2&steps=60", timeout=60)
    check_explored(figures)
    doc = figures[0][0]
    assert mapped.status_code == 200, mapped.text
    want = robustness(doc.spec, doc.weights, poses=2, steps=60, world=doc.world)
    assert mapped.json() == {**want.as_dict(), "sha256": sha}


def test_a_studys_exploration_without_workers_is_colony_evaluates(tmp_path: Path) -> None:
    """No zenoh: the in-process executors take the report's jobs."""
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}", port=free_port(), executors=2, zenoh=False
    )
    with serving(settings) as (url, _):
        check_explored(study_figures(url))
