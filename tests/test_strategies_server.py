"""Strategies through the server's run manager and scheduler: each non-GA strategy's run,
evaluated job by job (the real evaluation), stores the champion `colony evolve` exports, also
when the manager is replaced mid-run (a restart resumes the strategy by replaying what the
store holds); such runs never go out as spans, and their stored parents are none; the archive
endpoint serves `colony evolve`'s archive."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
import sqlalchemy as sa

from evorobotics.document import controller_sha256
from evorobotics.evolution import evolve
from schemas.run import RunConfig, StrategyConfig, StrategyName, ValidationConfig
from server.core.settings import Settings
from server.runs import crud
from server.runs.lifecycle import RunManager
from tests.helpers import completed_run, drain, evaluated, free_port, serving

CONFIG = RunConfig(
    population=8,
    generations=4,
    trials=1,
    steps=15,
    job_size=3,
    validation=ValidationConfig(poses=3, steps=30, candidates=3),
    strategy_settings=StrategyConfig(cells=5, emitters=2, novelty_k=3, novelty_add=2),
)
BASE: dict[str, Any] = {"db_url": "unused", "span_below_seconds": 0.0, "spot_checks": 0}


@pytest.fixture
def make_manager(engine: sa.Engine) -> Callable[[], RunManager]:
    return lambda: RunManager(engine, Settings(**BASE))


def _champion(manager: RunManager, run_id: int) -> str | None:
    with manager.sessions() as session:
        run = crud.get_run(session, run_id=run_id)
        assert run is not None and run.status == "completed"
        return run.champion_sha256


@pytest.mark.parametrize("strategy", ["cma-es", "sep-cma-es", "map-elites", "cma-me", "novelty"])
def test_a_strategy_run_on_the_server_stores_evolve_s_champion_across_a_restart(
    make_manager: Callable[[], RunManager], strategy: StrategyName
) -> None:
    """Two workers share each generation in slices; the manager is replaced after two."""
    config = CONFIG.model_copy(update={"strategy": strategy})
    expected = evolve(config).best.sha256
    first = make_manager()
    for worker in ("a", "b"):
        first.scheduler.join(worker)
    run_id = first.create_run(config)
    for _ in range(2):  # two generations, each in two workers' slices
        for worker in ("a", "b"):
            result = evaluated(first, worker)
            assert result is not None and result.start is not None and result.stop is not None
            assert result.stop - result.start == 4  # two slices of a generation of 8
            assert first.scheduler.settle(result).accepted
    first.stop()  # writes the two told generations
    with first.sessions() as session:
        stored = crud.ranked(session, run_id=run_id, generation=1)[0]
        assert (stored.parent == -1).all()  # no Eq 11 lineage outside the paper's GA
    second = make_manager()
    second.recover()  # the strategy replayed from the two stored generations
    drain(second)
    assert _champion(second, run_id) == expected


def test_a_strategy_run_is_never_leased_as_a_span(engine: sa.Engine) -> None:
    """Workers evolve spans with the paper's GA only: a CMA-ES run beside a GA run, both whole
    generations for two fast workers, goes out one generation at a time."""
    manager = RunManager(engine, Settings(**{**BASE, "span_below_seconds": 1e9}))
    for worker in ("a", "b"):
        manager.scheduler.join(worker, speed=1e9)
    ga = manager.create_run(CONFIG)
    cma = manager.create_run(CONFIG.model_copy(update={"strategy": "cma-es"}))
    first, second = manager.scheduler.lease("a"), manager.scheduler.lease("b")
    assert first is not None and second is not None
    jobs = {job.key.run_id: job for job in (first, second)}
    assert jobs.keys() == {ga, cma}
    assert (jobs[ga].start, jobs[ga].stop, jobs[ga].span) == (0, 8, CONFIG.generations)
    assert (jobs[cma].start, jobs[cma].stop, jobs[cma].span) == (0, 8, 1)
    assert jobs[cma].state is None


def test_the_archive_endpoint_serves_evolve_s_archive_and_404s_without_one(tmp_path: Path) -> None:
    """GET /api/runs/{id}/archive on a real server: a map-elites run's elites with the
    descriptors, fitness and controller sha256 of `colony evolve`'s archive; a paper-ga run
    and an unknown run are 404s naming why."""
    config = CONFIG.model_copy(update={"strategy": "map-elites"})
    archive = evolve(config).archive
    assert archive is not None
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'a.db'}",
        port=free_port(),
        workers=0,
        zenoh=False,
        executors=1,
    )
    with serving(settings) as (url, _):
        qd = completed_run(url, config.model_dump(mode="json"))
        ga = completed_run(url, CONFIG.model_dump(mode="json"))
        with httpx.Client(base_url=url, timeout=30) as client:
            served = client.get(f"/api/runs/{qd}/archive").json()
            missing = client.get(f"/api/runs/{ga}/archive")
            unknown = client.get("/api/runs/999/archive")
    assert served["generation"] == CONFIG.generations
    assert served["axes"] == list(config.strategy_settings.axes)
    spec = config.network_spec
    assert served["cells"] == [
        {"descriptors": d.tolist(), "fitness": float(f), "sha256": controller_sha256(spec, g)}
        for d, f, g in zip(archive.descriptors, archive.fitness, archive.genomes, strict=True)
    ]
    assert missing.status_code == 404 and "paper-ga keeps no archive" in missing.text
    assert unknown.status_code == 404
