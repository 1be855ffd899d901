"""The server's validated champion: a completed run's best is `evolution.champion` of its last
generation (with `validation`), found again after a restart and sent by "push the run's best";
a live run's best is training rank 0. Real SQLite files, the real RunManager, real zenoh."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx
import sqlalchemy as sa

from evorobotics.document import ControllerDocument, controller_sha256
from evorobotics.evaluate import evaluate
from evorobotics.evolution import RunLoop, champion
from schemas.run import RunConfig, ValidationConfig
from server.core.db import make_engine, upgrade
from server.core.settings import Settings
from server.robots.replacement import ranked_document
from server.runs import crud
from server.runs.lifecycle import RunManager
from tests.helpers import (
    WAIT,
    Colony,
    completed_run,
    drain,
    evaluated,
    eventually,
    free_port,
    online,
    robot_link,
    serving,
    virtual_robot,
)

RUN: dict[str, Any] = {
    "population": 8,
    "generations": 2,
    "steps": 5,
    "job_size": 4,
    "seed": 0,
    "validation": {"poses": 5, "steps": 20},
}
"""Seed 0: its champion is training rank 1, so serving rank 0 instead would be caught."""
CONFIG = RunConfig.model_validate(RUN)
SETTINGS = Settings(db_url="unused", max_attempts=2, span_below_seconds=0.0)


def local_champion(run_id: int) -> ControllerDocument:
    """`champion` of the run's last generation, evolved here by the run loop."""
    loop = RunLoop(CONFIG)
    while True:
        scored = evaluate(CONFIG, loop.generation, loop.ask())
        told = loop.tell(scored.fitness, scored.components)
        if loop.done:
            break
    return champion(
        CONFIG,
        told.genomes,
        told.fitness,
        told.metrics.order,
        generation=told.generation,
        run=run_id,
    )


def engine_in(tmp_path: Path) -> sa.Engine:
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    upgrade(engine)
    return engine


def test_the_validation_set_picks_another_rank_than_training() -> None:
    """The precondition that lets the tests below tell a champion from training rank 0."""
    validation = local_champion(1).validation
    assert validation is not None and validation.training_rank != 0
    assert CONFIG.validation == ValidationConfig(poses=5, steps=20)


def test_live_best_is_rank_0_and_a_completed_run_serves_its_champion_after_a_restart(
    tmp_path: Path,
) -> None:
    engine = engine_in(tmp_path)
    manager = RunManager(engine, SETTINGS)
    run_id = manager.create_run(CONFIG)
    for _ in range(2):  # generation 0's two jobs
        result = evaluated(manager, "w")
        assert result is not None and manager.scheduler.settle(result).accepted
    manager.flush()
    live = manager.best(run_id)
    assert live.validation is None and live.provenance["generation"] == 0
    with manager.sessions() as session:
        genomes = crud.ranked(session, run_id=run_id, generation=0, rank=0)[1]
    assert live.sha256 == controller_sha256(CONFIG.network_spec, genomes[0])

    drain(manager)
    expected = local_champion(run_id)
    served = manager.best(run_id)
    assert served.validation is not None
    assert served.to_json() == expected.to_json()
    with manager.sessions() as session:
        stored = crud.get_controller(session, sha256=expected.sha256)
        assert stored is not None and stored.document == expected.to_json()

    restarted = RunManager(engine, SETTINGS)
    restarted.recover()
    assert restarted.best(run_id).to_json() == expected.to_json()
    engine.dispose()


def test_a_champion_replaces_its_rank_document_and_an_unnamed_one_is_chosen_at_start(
    tmp_path: Path,
) -> None:
    """A completed run without a named champion (its push stored the champion's controller
    without `validation`) gets it when the server starts: its stages are jobs again, chosen
    from the stored last generation."""
    engine = engine_in(tmp_path)
    manager = RunManager(engine, SETTINGS)
    run_id = manager.create_run(CONFIG)
    drain(manager)
    expected = local_champion(run_id)
    assert expected.validation is not None
    with manager.sessions.begin() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and run.champion_sha256 == expected.sha256
        run.champion_sha256 = None
        row = crud.get_controller(session, sha256=expected.sha256)
        assert row is not None
        session.delete(row)
        session.flush()
        pushed = ranked_document(session, run_id, expected.validation.training_rank)
    assert pushed.sha256 == expected.sha256 and pushed.validation is None
    assert manager.best(run_id).validation is None  # unnamed: training rank 0, as a live run

    restarted = RunManager(engine, SETTINGS)
    restarted.recover()
    assert restarted.best(run_id).validation is None  # until its stages are done
    drain(restarted)
    assert restarted.best(run_id).to_json() == expected.to_json()
    with restarted.sessions() as session:
        stored = crud.get_controller(session, sha256=expected.sha256)
        assert stored is not None and stored.document == expected.to_json()
    engine.dispose()


def test_pushing_a_runs_best_sends_its_champion_and_a_rank_that_rank(tmp_path: Path) -> None:
    (tmp_path / "server").mkdir()
    db_url = f"sqlite:///{tmp_path / 'server' / 'colony.db'}"  # its key apart from the robot's
    settings = Settings(db_url=db_url, port=free_port(), executors=1, zenoh=False)
    with serving(settings) as (url, app), httpx.Client(base_url=url, timeout=30) as client:
        run_id = completed_run(url, RUN)
        best = client.get(f"/api/runs/{run_id}/best").json()
        assert best["validation"] == local_champion(run_id).to_dict()["validation"]
        ranked = client.get(f"/api/runs/{run_id}/individuals").json()["individuals"]
        colony = Colony(url, db_url, run_id, app, tmp_path)
        with robot_link(colony) as link, virtual_robot("r-best", link, tmp_path) as (agent, _):
            assert eventually(lambda: online(client, "r-best"), WAIT)
            pushed = client.post("/api/robots/r-best/controller", json={"run_id": run_id})
            assert pushed.status_code == 200, pushed.text
            assert pushed.json()["accepted"] and pushed.json()["sha256"] == best["sha256"]
            assert agent.controller is not None and agent.controller.sha256 == best["sha256"]
            assert agent.controller.validation is not None
            rank0 = client.post("/api/robots/r-best/controller", json={"run_id": run_id, "rank": 0})
            assert rank0.status_code == 200, rank0.text
            assert rank0.json()["sha256"] == ranked[0]["sha256"] != best["sha256"]
            assert agent.controller.provenance["rank"] == 0 and agent.controller.validation is None
            beyond = client.post(
                "/api/robots/r-best/controller", json={"run_id": run_id, "rank": 8}
            )
            assert beyond.status_code == 404 and "rank 8" in beyond.json()["detail"]
        stored = client.get(f"/api/controllers/{best['sha256']}").json()
        assert stored["validation"] == best["validation"]
        assert ranked[best["validation"]["training_rank"]]["sha256"] == best["sha256"]
