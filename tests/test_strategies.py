"""Every strategy behind the one RunLoop: determinism, no global random state, resume by replay,
archives, and `colony evolve --strategy` writing archive.csv and archive.png."""

import csv
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from colony.cli import app
from evorobotics.document import controller_sha256
from evorobotics.evolution import EvolutionResult, RunLoop, StrategyHistory, evolve
from evorobotics.strategies import novelty
from schemas.run import RunConfig, StrategyConfig, StrategyName, ValidationConfig

STRATEGIES: tuple[StrategyName, ...] = (
    "paper-ga",
    "cma-es",
    "sep-cma-es",
    "map-elites",
    "cma-me",
    "novelty",
)
WITH_ARCHIVE = ("map-elites", "cma-me", "novelty")

TINY = RunConfig(
    population=8,
    generations=3,
    trials=1,
    steps=15,
    validation=ValidationConfig(poses=3, steps=30, candidates=3),
    strategy_settings=StrategyConfig(cells=5, emitters=2, novelty_k=3, novelty_add=2),
)


def tiny(strategy: StrategyName, seed: int = 0) -> RunConfig:
    return TINY.model_copy(update={"strategy": strategy, "seed": seed})


def fake_told(genomes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fitness and descriptors in [0, 1], functions of each genome alone (no simulation)."""
    fitness = np.sin(genomes).sum(axis=1) + genomes[:, 0] ** 2
    descriptors = 1.0 / (1.0 + np.exp(-genomes[:, :4]))
    return fitness, descriptors


def tell_fake(loop: RunLoop) -> None:
    fitness, descriptors = fake_told(loop.ask())
    loop.tell(fitness, None, descriptors)


def archive_bytes(result: EvolutionResult) -> bytes:
    a = result.archive
    return b"" if a is None else a.descriptors.tobytes() + a.fitness.tobytes() + a.genomes.tobytes()


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_same_seed_same_champion_and_archive_other_seed_differs(strategy: StrategyName) -> None:
    np.random.seed(1)
    before = np.random.get_state()
    first = evolve(tiny(strategy))
    after = np.random.get_state()
    assert all(np.array_equal(x, y) for x, y in zip(before, after, strict=True))  # untouched
    again = evolve(tiny(strategy))
    other = evolve(tiny(strategy, seed=1))
    assert first.best.sha256 == again.best.sha256
    assert archive_bytes(first) == archive_bytes(again)
    assert first.best.sha256 != other.best.sha256
    assert (first.archive is not None) == (strategy in WITH_ARCHIVE)
    if first.archive is not None:
        a = first.archive
        assert a.descriptors.shape == (len(a.fitness), 2) and a.genomes.shape[0] == len(a.fitness)
        assert ((a.descriptors >= 0) & (a.descriptors <= 1)).all()
        assert archive_bytes(first) != archive_bytes(other)
        # the champion is an archive elite (novelty: or a member of the final generation)
        pool = np.concatenate([a.genomes, first.genomes])
        assert any(np.array_equal(g, first.best.weights) for g in pool)


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_global_random_state_never_changes_a_run(strategy: StrategyName) -> None:
    config = tiny(strategy).model_copy(update={"generations": 4})
    runs = []
    for reseed in (0, 1):
        loop = RunLoop(config)
        asked = []
        while not loop.done:
            np.random.seed(1000 * reseed + loop.generation)
            genomes = loop.ask()
            asked.append(genomes.copy())
            np.random.seed(7 + reseed)
            tell_fake(loop)
        runs.append(np.stack(asked))
    assert runs[0].shape == (4, config.population, config.network_spec.weight_count)
    assert runs[0].tobytes() == runs[1].tobytes()


@settings(max_examples=12, deadline=None)
@given(strategy=st.sampled_from(STRATEGIES), k=st.integers(0, 5))
def test_resume_from_history_after_k_generations_equals_uninterrupted(
    strategy: StrategyName, k: int
) -> None:
    config = tiny(strategy).model_copy(update={"generations": 6})
    straight = RunLoop(config)
    expected = []
    while not straight.done:
        genomes = straight.ask()
        fitness, descriptors = fake_told(genomes)
        expected.append(straight.tell(fitness, None, descriptors).genomes)
    loop = RunLoop(config)
    for _ in range(k):
        tell_fake(loop)
    stored = {name: a.copy() for name, a in loop.history.to_arrays().items()}
    resumed = RunLoop.resume(config, StrategyHistory.from_arrays(stored))
    assert resumed.generation == k
    told = []
    while not resumed.done:
        genomes = resumed.ask()
        fitness, descriptors = fake_told(genomes)
        told.append(resumed.tell(fitness, None, descriptors).genomes)
    assert b"".join(g.tobytes() for g in told) == b"".join(g.tobytes() for g in expected[k:])
    assert resumed.history.fitness.tobytes() == straight.history.fitness.tobytes()
    a, b = resumed.archive(), straight.archive()
    assert (a is None) == (b is None) == (strategy not in WITH_ARCHIVE)
    if a is not None and b is not None:
        assert a.genomes.tobytes() == b.genomes.tobytes()
        assert a.fitness.tobytes() == b.fitness.tobytes()


@pytest.mark.parametrize("strategy", ["cma-es", "map-elites", "novelty"])
def test_non_ga_loops_resume_from_history_only(strategy: StrategyName) -> None:
    config = tiny(strategy)
    loop = RunLoop(config)
    tell_fake(loop)
    with pytest.raises(ValueError, match="resumes from its history"):
        RunLoop(config, loop.state)
    with pytest.raises(ValueError, match="history of"):
        RunLoop.resume(tiny(strategy).model_copy(update={"population": 9}), loop.history)


@pytest.mark.parametrize("strategy", ["map-elites", "cma-me", "novelty"])
def test_archive_strategies_need_descriptors_and_may_be_told_again(
    strategy: StrategyName,
) -> None:
    loop = RunLoop(tiny(strategy))
    genomes = loop.ask()
    fitness, descriptors = fake_told(genomes)
    with pytest.raises(ValueError, match="needs the evaluation's descriptors"):
        loop.tell(fitness)
    assert loop.generation == 0 and loop.ask() is genomes
    assert loop.tell(fitness, None, descriptors).generation == 0 and loop.generation == 1


def test_novelty_is_the_mean_distance_to_the_k_nearest_others() -> None:
    archive = np.array([[0.0, 0.0], [1.0, 0.0]])
    behaviours = np.array([[0.0, 1.0], [0.0, 2.0], [np.nan, 0.0]])
    score = novelty(behaviours, archive, 2)
    assert score[0] == pytest.approx((1.0 + 1.0) / 2)  # (0,0) and (0,2), not itself
    assert score[1] == pytest.approx((1.0 + 2.0) / 2)  # (0,1) and (0,0)
    assert np.isnan(score[2])
    assert novelty(np.array([[0.5, 0.5]]), np.empty((0, 2)), 3).tolist() == [0.0]


def test_every_generation_asks_exactly_the_population() -> None:
    for strategy in STRATEGIES:
        config = tiny(strategy).model_copy(update={"population": 9})
        loop = RunLoop(config)
        while not loop.done:
            assert loop.ask().shape == (9, config.network_spec.weight_count), strategy
            tell_fake(loop)


def test_strategy_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="two different descriptors"):
        StrategyConfig(axes=("coverage", "coverage"))
    with pytest.raises(ValueError, match="too small for 5 emitters"):
        RunConfig(population=9, strategy="cma-me", strategy_settings=StrategyConfig(emitters=5))
    with pytest.raises(ValueError, match="MiB"):
        RunConfig(strategy="map-elites", strategy_settings=StrategyConfig(cells=500))
    with pytest.raises(ValueError, match="use sep-cma-es"):
        RunConfig(strategy="cma-es", network="paper-largest")
    RunConfig(strategy="sep-cma-es", network="paper-largest")
    with pytest.raises(ValueError, match="archive entries"):
        RunConfig(strategy="novelty", generations=100_000)
    RunConfig(strategy="paper-ga", generations=100_000)  # settings of other strategies: unread


def test_cli_strategy_flag_writes_the_archive(tmp_path: Path) -> None:
    args = ["evolve", "--population", "8", "--generations", "2", "--steps", "15", "--trials", "1"]
    config = tmp_path / "config.json"
    config.write_text(TINY.model_dump_json())
    result = CliRunner().invoke(
        app, [*args, "--strategy", "map-elites", "--config", str(config), "--out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    assert "strategy map-elites" in result.output
    rows = list(csv.reader((tmp_path / "archive.csv").read_text().splitlines()))
    assert rows[0] == ["final_x", "final_y", "fitness", "sha256"]
    assert len(rows) > 1 and (tmp_path / "archive.png").stat().st_size > 0
    resolved = RunConfig.model_validate_json((tmp_path / "config.json").read_text())
    assert resolved.strategy == "map-elites"
    replay = evolve(resolved)
    assert replay.archive is not None
    shas = [controller_sha256(resolved.network_spec, g) for g in replay.archive.genomes]
    assert [r[3] for r in rows[1:]] == shas
    assert [float(r[2]) for r in rows[1:]] == replay.archive.fitness.tolist()
