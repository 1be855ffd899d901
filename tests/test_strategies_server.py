"""Strategies through the server's run manager and scheduler: each non-GA strategy's run,
evaluated job by job (the real evaluation), stores the champion `colony evolve` exports, also
when the manager is replaced mid-run (a restart resumes the strategy by replaying what the
store holds); such runs never go out as spans, and their stored parents are none."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
import sqlalchemy as sa

from evorobotics.evolution import evolve
from schemas.run import RunConfig, StrategyConfig, StrategyName, ValidationConfig
from server import crud
from server.manager import RunManager
from server.settings import Settings
from tests.helpers import drain, evaluated

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


@pytest.mark.parametrize("strategy", ["cma-es", "map-elites", "novelty"])
def test_a_strategy_run_on_the_server_stores_evolve_s_champion_across_a_restart(
    make_manager: Callable[[], RunManager], strategy: StrategyName
) -> None:
    config = CONFIG.model_copy(update={"strategy": strategy})
    expected = evolve(config).best.sha256
    first = make_manager()
    run_id = first.create_run(config)
    while (result := evaluated(first, "w")) is not None and result.key.generation < 2:
        assert first.scheduler.settle(result).accepted
    first.stop()  # writes the two told generations; generation 2's result is never settled
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
