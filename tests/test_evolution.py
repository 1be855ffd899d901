"""Local evolution: job slices and the shared run loop."""

from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.evaluate import evaluate, map_slices, thread_slices
from evorobotics.evolution import (
    GenerationSummary,
    RunLoop,
    best_document,
    champion,
    evaluate_population,
    evolve,
    job_slices,
    validate,
)
from evorobotics.ga import GAParams, GAState, ask, ga_rng, init, tell
from evorobotics.layout import layout
from schemas.run import GAConfig, RunConfig


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


def _manual(
    config: RunConfig,
) -> tuple[np.ndarray, np.ndarray, list[tuple[int, float]], np.ndarray]:
    """The documented loop, each generation evaluated job by job as the server dispatches it."""
    lay = layout(config.network_spec)
    params = GAParams.from_config(config)
    state = init(lay, params)
    rows = []
    genomes = fitness = order = np.empty(0)
    for g in range(config.generations):
        genomes, state = ask(ga_rng(config.seed, g), state, params, lay)
        jobs = job_slices(config.population, config.job_size)
        fitness = np.concatenate([evaluate(config, g, genomes[a:b]).fitness for a, b in jobs])
        state, metrics = tell(genomes, fitness, state, params)
        rows.append((g, metrics.best))
        order = metrics.order
    return genomes, fitness, rows, order


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
    genomes, fitness, rows, order = _manual(SMALL)
    assert np.array_equal(result.genomes, genomes)
    assert result.fitness.tobytes() == fitness.tobytes()
    assert [(h.generation, h.best) for h in result.history] == rows
    assert tuple(seen) == result.history
    champ = champion(SMALL, genomes, fitness, order, generation=3)
    assert result.best == champ and champ.validation is not None
    rank = champ.validation.training_rank
    assert np.array_equal(result.best.weights, genomes[order[rank]])
    assert result.best.fitness == fitness[order[rank]]
    assert result.best.provenance == {"seed": 7, "generation": 3, "rank": rank, "run": "local"}
    assert result.components.shape == (12, SMALL.trials, 4)


@given(n=st.integers(0, 3000), threads=st.integers(1, 8), most=st.none() | st.integers(1, 400))
def test_thread_slices_share_the_rows_evenly_in_order(
    n: int, threads: int, most: int | None
) -> None:
    slices = thread_slices(n, threads, most)
    assert slices[0][0] == 0 and slices[-1][1] == n
    assert all(b == c for (_, b), (c, _) in pairwise(slices))
    sizes = [b - a for a, b in slices]
    if n == 0:
        assert slices == [(0, 0)]
        return
    assert min(sizes) >= 1 and max(sizes) - min(sizes) <= 1
    assert len(slices) % threads == 0 or len(slices) == n  # each thread as many slices
    if most is not None:
        assert max(sizes) <= most
        assert len(slices) < threads + -(-n // most)  # no more than needed
    else:
        assert len(slices) == min(n, threads)


def test_thread_slices_and_map_slices_examples() -> None:
    assert thread_slices(100, 2) == [(0, 50), (50, 100)]
    assert thread_slices(100, 2, 34) == [(0, 25), (25, 50), (50, 75), (75, 100)]
    assert thread_slices(3, 4) == [(0, 1), (1, 2), (2, 3)]
    slices = thread_slices(1000, 3, 7)
    assert map_slices(lambda a, b: (a, b), slices, 3) == slices
    for bad in ((10, 0, None), (10, 2, 0)):
        with pytest.raises(ValueError, match="must be >= 1"):
            thread_slices(*bad)


def test_a_slice_error_reaches_the_caller() -> None:
    def work(a: int, b: int) -> int:
        if a > 0:
            raise ArithmeticError(f"slice {a}")
        return b

    with pytest.raises(ArithmeticError, match="slice"):
        map_slices(work, thread_slices(10, 2), 2)


@settings(max_examples=10, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    population=st.integers(4, 40),
    threads=st.integers(2, 5),
    gap=st.booleans(),
)
def test_evaluate_is_the_same_on_any_number_of_threads(
    seed: int, population: int, threads: int, gap: bool
) -> None:
    # each robot's trial is independent of its batch-mates: slices on threads change nothing
    config = RunConfig(population=population, steps=30, seed=seed, reality_gap=gap)
    pop = np.random.default_rng(seed).normal(0.0, 1.5, (population, 222))
    one = evaluate(config, 3, pop)
    many = evaluate(config, 3, pop, threads=threads)
    for name in ("fitness", "components", "descriptors"):
        assert getattr(one, name).tobytes() == getattr(many, name).tobytes(), name


def test_validation_is_the_same_on_any_number_of_threads() -> None:
    config = SMALL.model_copy(
        update={"validation": SMALL.validation.model_copy(update={"poses": 5, "steps": 200})}
    )
    pop = np.random.default_rng(5).normal(0.0, 1.5, (9, 222))
    one = validate(config, pop)
    for threads in (2, 3):
        many = validate(config, pop, threads=threads)
        assert one.score.tobytes() == many.score.tobytes()
        assert one.stuck.tobytes() == many.stuck.tobytes()
        assert one.roaming.tobytes() == many.roaming.tobytes()


def test_evolve_is_the_same_on_one_thread_and_two() -> None:
    one, two = evolve(SMALL, threads=1), evolve(SMALL, threads=2)
    assert one.best.sha256 == two.best.sha256
    assert one.fitness.tobytes() == two.fitness.tobytes()
    assert one.components.tobytes() == two.components.tobytes()
    assert one.history == two.history


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
    second = best_document(SMALL, genomes, fitness, np.array([1, 2, 0]), generation=5, rank=1)
    assert np.array_equal(second.weights, genomes[2]) and second.provenance["rank"] == 1


def test_best_document_rejects_bad_arguments() -> None:
    genomes = np.zeros((3, 222))
    with pytest.raises(ValueError, match="outside the 0 ranked"):
        best_document(SMALL, genomes, np.zeros(3), np.array([], dtype=int), generation=0)
    with pytest.raises(ValueError, match="rank 3 is outside"):
        best_document(SMALL, genomes, np.zeros(3), np.array([0, 1, 2]), generation=0, rank=3)
    with pytest.raises(ValueError, match="fitness"):
        best_document(SMALL, genomes, np.zeros(2), np.array([0]), generation=0)
    with pytest.raises(ValueError, match="generation"):
        best_document(SMALL, genomes, np.zeros(3), np.array([0]), generation=-1)


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    generation=st.integers(0, 500),
    scale=st.floats(0.05, 3.0),
    cuts=st.lists(st.integers(1, 10), max_size=6),
    trials=st.integers(1, 4),
    gap=st.booleans(),
)
def test_evaluate_population_equals_any_slicing(
    seed: int, generation: int, scale: float, cuts: list[int], trials: int, gap: bool
) -> None:
    # trial conditions are per generation and robots independent: one call for the whole
    # population is bit-identical to any cut into jobs, concatenated in order
    config = RunConfig(population=11, steps=30, trials=trials, seed=seed, reality_gap=gap)
    genomes = np.random.default_rng(seed).normal(0.0, scale, (11, config.network_spec.weight_count))
    fitness, components, descriptors = evaluate_population(config, generation, genomes)
    bounds = [0, *sorted(set(cuts)), 11]
    parts = [evaluate(config, generation, genomes[a:b]) for a, b in pairwise(bounds)]
    assert fitness.shape == (11,) and components.shape == (11, trials, 4)
    assert descriptors.shape == (11, 4) and ((descriptors >= 0) & (descriptors <= 1)).all()
    assert np.concatenate([p.fitness for p in parts]).tobytes() == fitness.tobytes()
    assert np.concatenate([p.components for p in parts]).tobytes() == components.tobytes()
    assert np.concatenate([p.descriptors for p in parts]).tobytes() == descriptors.tobytes()


def test_evaluate_population_needs_one_row_per_individual() -> None:
    genomes = np.zeros((SMALL.population + 1, SMALL.network_spec.weight_count))
    with pytest.raises(ValueError, match="one row per individual"):
        evaluate_population(SMALL, 0, genomes)
    with pytest.raises(ValueError, match="one row per individual"):
        evaluate_population(SMALL, 0, genomes[0])


LOOPED = RunConfig(population=6, generations=4, steps=5, trials=1)


def _states_equal(a: GAState, b: GAState) -> bool:
    arrays_a, arrays_b = a.to_arrays(), b.to_arrays()
    return arrays_a.keys() == arrays_b.keys() and all(
        arrays_a[k].dtype == arrays_b[k].dtype and arrays_a[k].tobytes() == arrays_b[k].tobytes()
        for k in arrays_a
    )


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    selection=st.sampled_from(["prose", "literal"]),
    fitness=st.lists(
        st.lists(st.floats(-1e6, 1e6) | st.just(np.nan), min_size=6, max_size=6),
        min_size=4,
        max_size=4,
    ),
    stop=st.integers(0, 4),
)
def test_a_loop_rebuilt_from_any_state_goes_on_bit_for_bit(
    seed: int, selection: str, fitness: list[list[float]], stop: int
) -> None:
    """A RunLoop rebuilt from any intermediate state, through its arrays (what the server
    stores and a span's worker receives), asks and tells exactly what the uninterrupted loop
    does: any fitness, NaN (a failed evaluation) and ties included."""
    config = LOOPED.model_copy(update={"seed": seed, "ga": GAConfig(selection=selection)})
    values = [np.array(row, dtype=np.float64) for row in fitness]
    straight = RunLoop(config)
    expected = []
    while not straight.done:
        expected.append(straight.tell(values[straight.generation]))
    assert straight.done and straight.generation == config.generations
    loop = RunLoop(config)
    told = [loop.tell(values[g]) for g in range(stop)]
    loop = RunLoop(config, GAState.from_arrays(loop.state.to_arrays()))
    assert loop.generation == stop
    while not loop.done:
        told.append(loop.tell(values[loop.generation]))
    for a, b in zip(told, expected, strict=True):
        assert a.generation == b.generation
        assert a.genomes.tobytes() == b.genomes.tobytes()
        assert a.metrics.order.tobytes() == b.metrics.order.tobytes()
        assert _states_equal(a.before, b.before) and _states_equal(a.after, b.after)
    assert _states_equal(loop.state, straight.state)
    with pytest.raises(ValueError, match="over"):
        loop.ask()


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    fitness=st.lists(
        st.lists(st.floats(-1e6, 1e6) | st.just(np.nan), min_size=6, max_size=6),
        min_size=4,
        max_size=4,
    ),
    ahead=st.integers(0, 4),
    diverge=st.integers(0, 4),
    asked=st.booleans(),
)
def test_a_loop_following_its_forks_steps_goes_on_bit_for_bit(
    seed: int, fitness: list[list[float]], ahead: int, diverge: int, asked: bool
) -> None:
    """A fork told `ahead` generations (the server's spot-check of a span), after which its
    loop is told the same fitness up to generation `diverge` and other fitness after: every
    generation is what a loop never forked asks and tells, and the steps the fork took are
    taken, not computed again (the very same states)."""
    config = LOOPED.model_copy(update={"seed": seed})
    values = [np.array(row, dtype=np.float64) for row in fitness]
    other = [np.where(np.isnan(row), 0.0, row) + 1.0 for row in values]
    told_values = [values[g] if g < diverge else other[g] for g in range(config.generations)]
    straight = RunLoop(config)
    expected = [straight.tell(told_values[g]) for g in range(config.generations)]
    loop = RunLoop(config)
    if asked:
        loop.ask()
    fork = loop.fork()
    forked = []
    for g in range(ahead):
        forked.append(fork.tell(values[g]))
        if not fork.done:
            fork.ask()
    told = [loop.tell(told_values[g]) for g in range(config.generations)]
    for g, (a, b) in enumerate(zip(told, expected, strict=True)):
        assert a.genomes.tobytes() == b.genomes.tobytes()
        assert a.metrics.order.tobytes() == b.metrics.order.tobytes()
        assert _states_equal(a.after, b.after)
        assert (g < ahead and a.after is forked[g].after) == (g < min(ahead, diverge))
    assert _states_equal(loop.state, straight.state)


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), generations=st.integers(1, 3))
def test_evolve_equals_the_manual_run_loop(seed: int, generations: int) -> None:
    """`evolve` is the ask / evaluate / tell loop over RunLoop, nothing more."""
    config = LOOPED.model_copy(update={"seed": seed, "generations": generations})
    result = evolve(config)
    loop = RunLoop(config)
    history = []
    while not loop.done:
        genomes = loop.ask()
        assert loop.ask() is genomes and not genomes.flags.writeable  # asked once, read-only
        fitness, components, descriptors = evaluate_population(config, loop.generation, genomes)
        told = loop.tell(fitness, components, descriptors)
        assert told.descriptors is descriptors
        history.append(told.summary())
    assert _states_equal(result.state, loop.state)
    assert result.genomes.tobytes() == told.genomes.tobytes()
    assert result.fitness.tobytes() == told.fitness.tobytes()
    assert result.components.tobytes() == components.tobytes()
    assert result.history == tuple(history)
    order = told.metrics.order
    best = champion(config, told.genomes, told.fitness, order, generation=told.generation)
    assert result.best.to_json() == best.to_json()
