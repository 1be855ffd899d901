"""Local evolution: job slices and the shared run loop."""

from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from evorobotics.evaluate import evaluate
from evorobotics.evolution import GenerationSummary, best_document, evolve, job_slices
from evorobotics.ga import GAParams, ask, ga_rng, init, tell
from evorobotics.layout import layout
from schemas.run import RunConfig


@given(population=st.integers(1, 5000), job_size=st.integers(1, 600))
def test_job_slices_partition_population_in_order(population: int, job_size: int) -> None:
    slices = job_slices(population, job_size)
    assert slices[0][0] == 0
    assert slices[-1][1] == population
    for (a, b), (c, _) in pairwise(slices):
        assert b == c
        assert b - a == job_size  # only the last slice may be short
    assert all(0 < b - a <= job_size for a, b in slices)
    assert len(slices) == -(-population // job_size)


def test_job_slices_examples() -> None:
    assert job_slices(100, 25) == [(0, 25), (25, 50), (50, 75), (75, 100)]
    assert job_slices(10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert job_slices(3, 50) == [(0, 3)]


@pytest.mark.parametrize(("population", "job_size"), [(0, 5), (-1, 5), (10, 0), (10, -3)])
def test_job_slices_reject_bad_arguments(population: int, job_size: int) -> None:
    with pytest.raises(ValueError, match="must be >= 1"):
        job_slices(population, job_size)


SMALL = RunConfig(population=12, generations=4, steps=20, job_size=5, seed=7)


def _manual(config: RunConfig) -> tuple[np.ndarray, np.ndarray, list[tuple[int, float]], int]:
    """The documented loop, but each generation evaluated as ONE job, not in job_size slices."""
    lay = layout(config.network_spec)
    params = GAParams.from_config(config)
    state = init(lay, params)
    rows = []
    genomes = fitness = np.empty(0)
    top = -1
    for g in range(config.generations):
        genomes, state = ask(ga_rng(config.seed, g), state, params, lay)
        whole = evaluate(config, g, genomes)
        fitness = whole.fitness
        state, metrics = tell(genomes, fitness, state, params)
        rows.append((g, metrics.best))
        top = int(metrics.order[0])
    return genomes, fitness, rows, top


def test_evolve_is_deterministic() -> None:
    a, b = evolve(SMALL), evolve(SMALL)
    assert np.array_equal(a.genomes, b.genomes)
    assert a.fitness.tobytes() == b.fitness.tobytes()
    assert a.components.tobytes() == b.components.tobytes()
    assert a.history == b.history
    assert a.best.sha256 == b.best.sha256
    other = evolve(SMALL.model_copy(update={"seed": 8}))
    assert not np.array_equal(a.genomes, other.genomes)


def test_evolve_equals_manual_composition_whatever_the_slicing() -> None:
    seen: list[GenerationSummary] = []
    result = evolve(SMALL, on_generation=seen.append)
    genomes, fitness, rows, top = _manual(SMALL)
    assert np.array_equal(result.genomes, genomes)
    assert result.fitness.tobytes() == fitness.tobytes()
    assert [(h.generation, h.best) for h in result.history] == rows
    assert tuple(seen) == result.history
    assert np.array_equal(result.best.weights, genomes[top])
    assert result.best.fitness == fitness[top] == max(fitness)
    assert result.best.provenance == {"seed": 7, "generation": 3, "rank": 0, "run": "local"}
    assert result.components.shape == (12, SMALL.trials, 4)


def test_history_statistics_are_ordered() -> None:
    for h in evolve(SMALL).history:
        assert h.worst <= h.mean <= h.best
        assert h.nan_count == 0


def test_best_document_takes_rank_zero() -> None:
    genomes = np.arange(3 * 222, dtype=np.float64).reshape(3, 222) / 1000
    fitness = np.array([1.0, 3.0, 2.0])
    doc = best_document(SMALL, genomes, fitness, np.array([1, 2, 0]), generation=5, run=42)
    assert np.array_equal(doc.weights, genomes[1])
    assert doc.fitness == 3.0
    assert doc.provenance == {"seed": 7, "generation": 5, "rank": 0, "run": 42}
    assert doc.spec == SMALL.network_spec


def test_best_document_rejects_bad_arguments() -> None:
    genomes = np.zeros((3, 222))
    with pytest.raises(ValueError, match="empty"):
        best_document(SMALL, genomes, np.zeros(3), np.array([], dtype=int), generation=0)
    with pytest.raises(ValueError, match="fitness"):
        best_document(SMALL, genomes, np.zeros(2), np.array([0]), generation=0)
    with pytest.raises(ValueError, match="generation"):
        best_document(SMALL, genomes, np.zeros(3), np.array([0]), generation=-1)
