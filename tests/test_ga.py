"""The genetic algorithm: Eq 7 initialisation, Eqs 9-10 mutation, Eq 11 next generation, state."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.ga import (
    GAParams,
    GAState,
    Selection,
    ask,
    ga_rng,
    init,
    initial_population,
    lineage,
    mutate,
    mutation_rate,
    tell,
    weight_scale,
)
from evorobotics.layout import Layout, layout
from schemas.network import PRESETS, NetworkSpec
from schemas.run import GAConfig, RunConfig

SMALL = layout(NetworkSpec(hidden=(3,), delays=1, recurrence=1))
DEEP = layout(NetworkSpec(hidden=(4, 4), delays=3, recurrence=2))


def make_params(n: int, m: int, selection: Selection = "prose", **kwargs: float) -> GAParams:
    ga = GAConfig().model_copy(update=kwargs)
    return GAParams(
        population=n,
        replacement=m,
        selection=selection,
        base_rate=ga.base_rate,
        eta=ga.eta,
        init_scale=ga.init_scale,
        layer_slope=ga.layer_slope,
        delay_decay=ga.delay_decay,
        recurrence_decay=ga.recurrence_decay,
    )


def reference_order(fitness: list[float]) -> list[int]:
    """Fittest first, ties in population order, NaN last: the ranking rule written plainly."""
    return sorted(
        range(len(fitness)),
        key=lambda i: (math.isnan(fitness[i]), 0.0 if math.isnan(fitness[i]) else -fitness[i]),
    )


def expected_lineage(
    n: int, m: int, selection: Selection, generation: int
) -> list[tuple[str, int]]:
    """Eq 11 spelt out with the paper's 1-based ranks, converted to 0-based at the end."""
    if generation == 0:
        return [("random", -1)] * n
    if selection == "prose":  # fittest remaining: ranks m+1 .. n-m-1 (n-m in generation 1)
        fill = range(m + 1, (n - m if generation == 1 else n - m - 1) + 1)
    else:  # as printed: ranks 2m+1 .. n-1 (n in generation 1)
        fill = range(2 * m + 1, (n if generation == 1 else n - 1) + 1)
    out = [("elite", r - 1) for r in range(1, m + 1)] + [("mutant", r - 1) for r in range(1, m + 1)]
    out += [("fill", r - 1) for r in fill]
    if generation >= 2:
        out.append(("elite_k2", -1))
    return out


fitness_value = st.one_of(
    st.sampled_from([math.nan, -math.inf, math.inf, 0.0, 1.0, -1.0]),
    st.floats(-5.0, 5.0, allow_nan=False),
)


@st.composite
def run_case(draw: st.DrawFn) -> tuple[int, int, Selection, list[list[float]]]:
    n = draw(st.integers(5, 60))
    m = draw(st.integers(1, (n - 1) // 2))
    selection: Selection = draw(st.sampled_from(["prose", "literal"]))
    fits = [draw(st.lists(fitness_value, min_size=n, max_size=n)) for _ in range(3)]
    return n, m, selection, fits


@settings(max_examples=40, deadline=None)
@given(case=run_case(), seed=st.integers(0, 2**32))
def test_eq11_composition_over_three_generations(
    case: tuple[int, int, Selection, list[list[float]]], seed: int
) -> None:
    n, m, selection, fits = case
    params = make_params(n, m, selection)
    state = init(SMALL, params)
    bound = params.eta * weight_scale(SMALL, params) / params.init_scale
    previous_best: np.ndarray | None = None
    for generation, fitness in enumerate(fits):
        assert state.generation == generation
        genomes, same = ask(ga_rng(seed, generation), state, params, SMALL)
        assert same is state
        assert genomes.shape == (n, SMALL.n_weights) and genomes.dtype == np.float64
        assert genomes.flags.c_contiguous
        expected = expected_lineage(n, m, selection, generation)
        assert lineage(params, generation) == expected
        kinds = [kind for kind, _ in expected]
        assert kinds.count("elite") == kinds.count("mutant") == (m if generation else 0)
        for i, (kind, parent) in enumerate(expected):
            if kind in ("elite", "fill"):
                assert state.ranked is not None
                assert np.array_equal(genomes[i], state.ranked[parent])
            elif kind == "mutant":
                assert state.ranked is not None
                assert np.all(np.abs(genomes[i] - state.ranked[parent]) <= bound)
            elif kind == "elite_k2":
                assert previous_best is not None
                assert np.array_equal(genomes[i], previous_best)
        previous_best = None if state.ranked is None else state.ranked[0].copy()

        f = np.array(fitness)
        state, metrics = tell(genomes, f, state, params)
        order = reference_order(fitness)
        assert metrics.order.tolist() == order
        assert metrics.generation == generation
        assert metrics.nan_count == int(np.isnan(f).sum())
        assert state.ranked is not None and state.ranked_fitness is not None
        assert np.array_equal(state.ranked, genomes[order])
        assert np.array_equal(state.ranked_fitness, f[order], equal_nan=True)
        if metrics.nan_count < n:  # NaN never wins, and sits after every real value
            assert not math.isnan(state.ranked_fitness[0])
            assert np.isnan(state.ranked_fitness[n - metrics.nan_count :]).all()
        finite = f[np.isfinite(f)]
        if finite.size:
            assert (metrics.best, metrics.worst) == (finite.max(), finite.min())
            assert metrics.mean == pytest.approx(finite.mean())
        else:
            assert math.isnan(metrics.best) and math.isnan(metrics.mean)


def test_k2_elite_is_best_of_two_generations_back_even_after_it_drops() -> None:
    n, m = 9, 2
    params = make_params(n, m)
    state = init(SMALL, params)
    gen0, state = ask(ga_rng(1, 0), state, params, SMALL)
    state, _ = tell(gen0, np.arange(n, dtype=np.float64), state, params)  # index 8 is best
    gen1, state = ask(ga_rng(1, 1), state, params, SMALL)
    state, _ = tell(gen1, np.arange(n, dtype=np.float64), state, params)  # gen0's best now worst
    gen2, state = ask(ga_rng(1, 2), state, params, SMALL)
    assert np.array_equal(gen1[0], gen0[8])
    assert not any(np.array_equal(row, gen0[8]) for row in gen2[:-1])
    assert np.array_equal(gen2[-1], gen0[8])


def run_generations(seed: int, generations: int, params: GAParams, lay: Layout) -> list[np.ndarray]:
    state = init(lay, params)
    populations = []
    for generation in range(generations):
        genomes, state = ask(ga_rng(seed, generation), state, params, lay)
        populations.append(genomes)
        state, _ = tell(genomes, np.sin(genomes.sum(axis=1)), state, params)
    return populations


def test_same_seed_bit_identical_different_seed_differs() -> None:
    params = make_params(20, 5)
    a = run_generations(7, 4, params, SMALL)
    b = run_generations(7, 4, params, SMALL)
    c = run_generations(8, 4, params, SMALL)
    for x, y, z in zip(a, b, c, strict=True):
        assert x.tobytes() == y.tobytes()
        assert not np.array_equal(x, z)


@pytest.mark.parametrize("selection", ["prose", "literal"])
def test_state_round_trip_through_raw_bytes_gives_identical_next_generation(
    selection: Selection,
) -> None:
    params = make_params(12, 3, selection)
    state = init(SMALL, params)
    for generation in range(4):
        stored = {
            name: (a.tobytes(), a.dtype.str, a.shape) for name, a in state.to_arrays().items()
        }
        restored = GAState.from_arrays(
            {
                name: np.frombuffer(raw, dtype=np.dtype(dtype)).reshape(shape)
                for name, (raw, dtype, shape) in stored.items()
            }
        )
        assert restored.generation == state.generation
        assert (restored.elite_k2 is None) == (generation < 2)
        genomes, state = ask(ga_rng(3, generation), state, params, SMALL)
        again, _ = ask(ga_rng(3, generation), restored, params, SMALL)
        assert genomes.tobytes() == again.tobytes()
        state, _ = tell(genomes, np.cos(genomes[:, 0]), state, params)


def test_state_arrays_are_read_only_copies() -> None:
    params = make_params(7, 2)
    state = init(SMALL, params)
    genomes, state = ask(ga_rng(0, 0), state, params, SMALL)
    fitness = np.arange(7, dtype=np.float64)
    state, metrics = tell(genomes, fitness, state, params)
    genomes[:] = 0.0
    fitness[:] = 0.0
    assert state.ranked is not None and state.ranked_fitness is not None
    assert state.ranked.any() and state.ranked_fitness[0] == 6.0
    for array in (state.ranked, state.ranked_fitness, metrics.order):
        assert not array.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 1
    arrays = state.to_arrays()
    assert arrays["generation"].shape == () and arrays["generation"].dtype == np.int64
    assert set(arrays) == {"generation", "n_weights", "ranked", "ranked_fitness"}
    without = state.to_arrays(ranked=False)
    assert set(without) == set(arrays) - {"ranked"}
    assert all(without[name].tobytes() == arrays[name].tobytes() for name in without)


def test_eq7_uniform_case_is_uniform_on_plus_minus_init_scale() -> None:
    params = make_params(400, 10, layer_slope=0.0, delay_decay=0.0, recurrence_decay=0.0)
    params = GAParams(**{**params.__dict__, "init_scale": 0.7})
    assert np.array_equal(weight_scale(DEEP, params), np.full(DEEP.n_weights, 0.7))
    w = initial_population(np.random.default_rng(5), DEEP, params)
    assert np.abs(w).max() <= 0.7
    counts, _ = np.histogram(w, bins=10, range=(-0.7, 0.7))
    assert np.allclose(counts / w.size, 0.1, rtol=0.05)


def test_eq7_magnitudes_shrink_with_depth_delay_and_recurrence() -> None:
    params = make_params(2000, 10)  # paper defaults: slope 0.25, decays 0.5
    scale = weight_scale(DEEP, params)
    w = initial_population(np.random.default_rng(11), DEEP, params)
    assert np.all(np.abs(w) <= scale)
    mean_abs = {(b.m, b.t, b.s): float(np.abs(DEEP.view(w, b)).mean()) for b in DEEP.blocks}
    for b in DEEP.blocks:  # uniform on [-a, a] has mean |w| = a / 2
        assert mean_abs[(b.m, b.t, b.s)] == pytest.approx(scale[b.offset] / 2, rel=0.05)
    for (m, t, s), value in mean_abs.items():
        for deeper in ((m + 1, t, s), (m, t + 1, s), (m, t, s + 1)):
            if deeper in mean_abs:
                assert mean_abs[deeper] < value
    first = DEEP.blocks[0]
    assert mean_abs[(first.m, first.t, first.s)] == pytest.approx(0.5, rel=0.02)


@settings(max_examples=50, deadline=None)
@given(
    slope=st.floats(0.0, 0.99),
    delay_decay=st.floats(0.0, 3.0),
    recurrence_decay=st.floats(0.0, 3.0),
    init_scale=st.floats(0.01, 10.0),
)
def test_eq7_scale_shape(
    slope: float, delay_decay: float, recurrence_decay: float, init_scale: float
) -> None:
    params = make_params(
        5,
        1,
        layer_slope=slope,
        delay_decay=delay_decay,
        recurrence_decay=recurrence_decay,
        init_scale=init_scale,
    )
    scale = weight_scale(DEEP, params)
    by_key = {(b.m, b.t, b.s): float(scale[b.offset]) for b in DEEP.blocks}
    assert by_key[(1, 0, 0)] == pytest.approx(init_scale)  # maxima of 1 at t = s = 0
    for (m, t, s), value in by_key.items():
        mu = value / (math.exp(-delay_decay * t) * math.exp(-recurrence_decay * s))
        assert mu >= 0.1 * init_scale * (1 - 1e-12)  # floored so deep layers keep some range
        for deeper in ((m + 1, t, s), (m, t + 1, s), (m, t, s + 1)):
            if deeper in by_key:
                assert by_key[deeper] <= value


@pytest.mark.parametrize("base_rate", [2.0, 8.0])
def test_eq9_mutation_frequency_per_block(base_rate: float) -> None:
    lay = layout(PRESETS["paper-best"])  # blocks of 9*6 = 54 and 2*10 = 20 weights
    params = make_params(5, 1, base_rate=base_rate)
    parents = np.zeros((20_000, lay.n_weights))
    _, mask = mutate(np.random.default_rng(2024), parents, lay, params)
    for block in lay.blocks:
        observed = lay.view(mask, block).mean()
        # about 40,000-160,000 expected flips per block: 3 % is over 5 standard deviations
        assert observed == pytest.approx(base_rate / block.size, rel=0.03)
        per_mutant = lay.view(mask, block).sum(axis=(1, 2)).mean()
        assert per_mutant == pytest.approx(base_rate, rel=0.03)


def test_eq9_rate_is_capped_at_one_for_small_blocks() -> None:
    lay = layout(NetworkSpec(inputs=1, hidden=(1,), outputs=1, delays=0))  # two blocks of 2
    params = make_params(5, 1, base_rate=3.0)
    assert np.array_equal(mutation_rate(lay, params), np.ones(lay.n_weights))
    _, mask = mutate(np.random.default_rng(0), np.zeros((50, lay.n_weights)), lay, params)
    assert mask.all()


def test_eq10_mutants_differ_only_where_p_is_one_within_the_step() -> None:
    params = make_params(5, 1, base_rate=4.0, init_scale=2.0)  # steps scale by eta, not init_scale
    parents = initial_population(np.random.default_rng(1), DEEP, make_params(300, 1))
    children, mask = mutate(np.random.default_rng(2), parents, DEEP, params)
    assert mask.any() and not mask.all()
    assert np.array_equal(children != parents, mask)
    step = np.abs(children - parents)
    bound = params.eta * weight_scale(DEEP, params) / params.init_scale
    assert np.all(step <= bound)
    # R spans [-1, 1): the largest layer-1 steps come close to eta
    assert step[:, DEEP.m == 1].max() > 0.95 * params.eta


def test_from_config_uses_replacement_count() -> None:
    params = GAParams.from_config(RunConfig())
    assert (params.population, params.replacement, params.selection) == (100, 25, "prose")
    assert (params.base_rate, params.eta, params.init_scale) == (8.0, 1.0, 1.0)
    small = GAParams.from_config(RunConfig(population=10, ga=GAConfig(selection="literal")))
    assert (small.population, small.replacement, small.selection) == (10, 2, "literal")


@pytest.mark.parametrize(
    ("n", "m", "kwargs", "message"),
    [
        (6, 3, {}, "n >= 2m\\+1"),
        (6, 0, {}, "replacement m must be >= 1"),
        (9, 2, {"eta": 0.0}, "eta must be > 0"),
        (9, 2, {"layer_slope": 1.0}, "layer_slope"),
        (9, 2, {"delay_decay": -0.1}, "delay_decay"),
    ],
)
def test_params_reject_bad_values(n: int, m: int, kwargs: dict[str, float], message: str) -> None:
    fields = {**make_params(9, 2).__dict__, "population": n, "replacement": m, **kwargs}
    with pytest.raises(ValueError, match=message):
        GAParams(**fields)


def test_bad_arguments_raise_value_error() -> None:
    params = make_params(7, 2)
    state = init(SMALL, params)
    genomes, _ = ask(ga_rng(0, 0), state, params, SMALL)
    with pytest.raises(ValueError, match="weights"):
        ask(ga_rng(0, 0), state, params, DEEP)
    with pytest.raises(ValueError, match="fitness has shape"):
        tell(genomes, np.zeros(6), state, params)
    with pytest.raises(ValueError, match="genomes have shape"):
        tell(genomes[:, :-1], np.zeros(7), state, params)
    with pytest.raises(ValueError, match="generation must be >= 0"):
        lineage(params, -1)
    arrays = tell(genomes, np.zeros(7), state, params)[0].to_arrays()
    with pytest.raises(ValueError, match="missing 'generation'"):
        GAState.from_arrays({k: v for k, v in arrays.items() if k != "generation"})
    with pytest.raises(ValueError, match="unknown"):
        GAState.from_arrays({**arrays, "extra": np.zeros(1)})
    with pytest.raises(ValueError, match="ranked has shape"):
        GAState.from_arrays({**arrays, "n_weights": np.array(3)})
    with pytest.raises(ValueError, match="k-2 elite"):
        GAState.from_arrays({**arrays, "generation": np.array(2)})
    with pytest.raises(ValueError, match="ranked_fitness must be given together"):
        GAState.from_arrays({k: v for k, v in arrays.items() if k != "ranked_fitness"})
    with pytest.raises(ValueError, match="population is 9"):
        ask(ga_rng(0, 1), GAState.from_arrays(arrays), make_params(9, 2), SMALL)
