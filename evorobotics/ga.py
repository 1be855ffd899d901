"""The genetic algorithm of paper section 2.3 (Eqs 7, 9, 10, 11) with explicit state.

evosax style: `init` -> `ask(rng, state, ...)` -> evaluate -> `tell(genomes, fitness, state, ...)`
-> `ask` ... The state is a frozen dataclass of read-only arrays that round-trips through plain
arrays (`to_arrays`/`from_arrays`), so the server can persist it after every generation and
resume bit-identically. Every random draw comes from the generator passed to `ask`; use
`ga_rng(seed, generation)`. See docs/ga.md for the equations as implemented.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

from evorobotics.layout import Layout
from evorobotics.seeds import Purpose, rng
from schemas.run import RunConfig

Selection = Literal["prose", "literal"]
LineageKind = Literal["random", "elite", "mutant", "fill", "elite_k2"]

MU_FLOOR = 0.1
"""Eq 7: mu(m) never falls below this fraction of init_scale, so deep layers keep some range."""


@dataclass(frozen=True)
class GAParams:
    """The GA's fixed knobs: n, m of Eq 11 and the Eq 7/9/10 constants (see schemas.run.GAConfig)."""

    population: int
    replacement: int
    selection: Selection
    base_rate: float
    eta: float
    init_scale: float
    layer_slope: float
    delay_decay: float
    recurrence_decay: float

    def __post_init__(self) -> None:
        if self.replacement < 1:
            raise ValueError(f"replacement m must be >= 1, got {self.replacement}")
        if self.population < 2 * self.replacement + 1:
            raise ValueError(
                f"population {self.population} is too small for replacement m = "
                f"{self.replacement}: Eq 11 needs n >= 2m+1"
            )
        if self.selection not in ("prose", "literal"):
            raise ValueError(f"selection must be 'prose' or 'literal', got {self.selection!r}")
        for name in ("base_rate", "eta", "init_scale"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.layer_slope < 1.0:
            raise ValueError(f"layer_slope must be in [0, 1), got {self.layer_slope}")
        for name in ("delay_decay", "recurrence_decay"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    @classmethod
    def from_config(cls, config: RunConfig) -> GAParams:
        """The params of a run: n = population, m = replacement_count, the rest from config.ga."""
        ga = config.ga
        return cls(
            population=config.population,
            replacement=config.replacement_count,
            selection=ga.selection,
            base_rate=ga.base_rate,
            eta=ga.eta,
            init_scale=ga.init_scale,
            layer_slope=ga.layer_slope,
            delay_decay=ga.delay_decay,
            recurrence_decay=ga.recurrence_decay,
        )


def _frozen(array: np.ndarray) -> np.ndarray:
    """A read-only float64 C-contiguous copy, so no caller can alter a stored state."""
    out = np.array(array, dtype=np.float64, order="C", copy=True)
    out.flags.writeable = False
    return out


@dataclass(frozen=True)
class GAState:
    """Everything needed to produce the next generation; persisted after every generation.

    `ranked` holds the previous generation sorted fittest first and `elite_k2` the best genome
    of the generation before it (Eq 11's p_1(k-2)). All arrays are read-only copies.
    """

    generation: int
    """The generation the next `ask` produces (0 first)."""
    ranked: np.ndarray | None
    """(n, n_weights) previous generation, fittest first; None before the first `tell`."""
    ranked_fitness: np.ndarray | None
    """(n,) fitness of `ranked` in the same order (NaN for failed evaluations)."""
    elite_k2: np.ndarray | None
    """(n_weights,) best genome of generation `generation - 2`; None until it exists."""
    n_weights: int

    def __post_init__(self) -> None:
        if self.generation < 0:
            raise ValueError(f"generation must be >= 0, got {self.generation}")
        if self.n_weights < 1:
            raise ValueError(f"n_weights must be >= 1, got {self.n_weights}")
        if (self.ranked is None) != (self.ranked_fitness is None):
            raise ValueError("ranked and ranked_fitness must be given together")
        if (self.ranked is None) != (self.generation == 0):
            raise ValueError(
                f"generation {self.generation} must have a ranked population "
                "exactly when it is not the first"
            )
        if (self.elite_k2 is None) != (self.generation < 2):
            raise ValueError(
                f"generation {self.generation} must have a k-2 elite exactly from generation 2 on"
            )
        if self.ranked is not None and self.ranked_fitness is not None:
            ranked, fitness = _frozen(self.ranked), _frozen(self.ranked_fitness)
            if ranked.ndim != 2 or ranked.shape[1] != self.n_weights or ranked.shape[0] < 1:
                raise ValueError(f"ranked has shape {ranked.shape}, expected (n, {self.n_weights})")
            if fitness.shape != (ranked.shape[0],):
                raise ValueError(
                    f"ranked_fitness has shape {fitness.shape}, expected ({ranked.shape[0]},)"
                )
            object.__setattr__(self, "ranked", ranked)
            object.__setattr__(self, "ranked_fitness", fitness)
        if self.elite_k2 is not None:
            elite = _frozen(self.elite_k2)
            if elite.shape != (self.n_weights,):
                raise ValueError(f"elite_k2 has shape {elite.shape}, expected ({self.n_weights},)")
            object.__setattr__(self, "elite_k2", elite)

    def to_arrays(self, *, ranked: bool = True) -> dict[str, np.ndarray]:
        """Plain arrays (0-d int64 for the integers), for storage as raw bytes; None is omitted.
        Without `ranked` (a store that keeps the population elsewhere: no copy of it is made)."""
        arrays = {
            "generation": np.array(self.generation, dtype=np.int64),
            "n_weights": np.array(self.n_weights, dtype=np.int64),
        }
        names = (
            ("ranked", "ranked_fitness", "elite_k2") if ranked else ("ranked_fitness", "elite_k2")
        )
        for name in names:
            value = getattr(self, name)
            if value is not None:
                arrays[name] = np.array(value, copy=True)
        return arrays

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> GAState:
        """The state `to_arrays` described; ValueError on missing keys or inconsistent shapes."""
        unknown = set(arrays) - {"generation", "n_weights", "ranked", "ranked_fitness", "elite_k2"}
        if unknown:
            raise ValueError(f"unknown GA state arrays: {sorted(unknown)}")
        ints: dict[str, int] = {}
        for name in ("generation", "n_weights"):
            if name not in arrays:
                raise ValueError(f"GA state is missing {name!r}")
            value = np.asarray(arrays[name])
            if value.shape != () or value.dtype.kind not in "iu":
                raise ValueError(
                    f"{name} must be a 0-d integer array, got {value.dtype}{value.shape}"
                )
            ints[name] = int(value)
        return cls(
            generation=ints["generation"],
            ranked=arrays.get("ranked"),
            ranked_fitness=arrays.get("ranked_fitness"),
            elite_k2=arrays.get("elite_k2"),
            n_weights=ints["n_weights"],
        )


@dataclass(frozen=True)
class TellMetrics:
    """What one `tell` saw: best/mean/worst over finite fitness values (NaN if there are none)."""

    generation: int
    best: float
    mean: float
    worst: float
    order: np.ndarray
    """Indices into the told genomes, fittest first (the ranking; NaN last)."""
    nan_count: int


def init(spec_layout: Layout, params: GAParams) -> GAState:
    """Generation 0: nothing ranked yet; the first `ask` draws the Eq 7 population."""
    del params  # part of the evosax-style signature; generation 0 needs only the weight count
    return GAState(
        generation=0,
        ranked=None,
        ranked_fitness=None,
        elite_k2=None,
        n_weights=spec_layout.n_weights,
    )


def weight_scale(spec_layout: Layout, params: GAParams) -> np.ndarray:
    """(n_weights,) mu(m) tau(t) sigma(s) of Eq 7: the half-range of each initial weight."""
    mu = params.init_scale * np.maximum(1.0 - params.layer_slope * (spec_layout.m - 1), MU_FLOOR)
    tau = np.exp(-params.delay_decay * spec_layout.t)
    sigma = np.exp(-params.recurrence_decay * spec_layout.s)
    scale: np.ndarray = mu * tau * sigma
    return scale


def mutation_rate(spec_layout: Layout, params: GAParams) -> np.ndarray:
    """(n_weights,) Eq 9: min(1, base_rate / (N*I)) with N*I the size of the weight's sub-matrix."""
    rate: np.ndarray = np.minimum(1.0, params.base_rate / spec_layout.block_size)
    return rate


def initial_population(
    rng: np.random.Generator, spec_layout: Layout, params: GAParams
) -> np.ndarray:
    """(n, n_weights) Eq 7: w = R mu(m) tau(t) sigma(s), R ~ U[-1, 1) drawn per weight."""
    shape = (params.population, spec_layout.n_weights)
    genomes: np.ndarray = rng.uniform(-1.0, 1.0, size=shape) * weight_scale(spec_layout, params)
    return genomes


def mutate(
    rng: np.random.Generator, parents: np.ndarray, spec_layout: Layout, params: GAParams
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs 9-10: (children, P) where c' = c + eta R P mu'(m) tau'(t) sigma'(s).

    mu' tau' sigma' is Eq 7's shape divided by init_scale (mu'(1) = 1), so eta alone sets the
    layer-1 step. Draws, in this order: P for every weight of every parent, then R.
    """
    if parents.ndim != 2 or parents.shape[1] != spec_layout.n_weights:
        raise ValueError(
            f"parents have shape {parents.shape}, expected (k, {spec_layout.n_weights})"
        )
    mask = rng.random(parents.shape) < mutation_rate(spec_layout, params)
    r = rng.uniform(-1.0, 1.0, size=parents.shape)
    step = params.eta * r * (weight_scale(spec_layout, params) / params.init_scale)
    children = np.where(mask, parents + step, parents)
    return children, mask


def _fill_ranks(params: GAParams, has_elite_k2: bool) -> np.ndarray:
    """0-based ranks of the previous generation that fill the rest of Eq 11's population."""
    n, m = params.population, params.replacement
    start = m if params.selection == "prose" else 2 * m
    count = n - 2 * m - (1 if has_elite_k2 else 0)
    return np.arange(start, start + count)


def ask(
    rng: np.random.Generator, state: GAState, params: GAParams, spec_layout: Layout
) -> tuple[np.ndarray, GAState]:
    """The population of generation `state.generation`: (n, n_weights) float64, C-contiguous.

    Generation 0 is Eq 7; later ones are Eq 11, ordered [m elites, their m mutants, fill in
    rank order, k-2 elite] (see `lineage`). The state is returned unchanged: the generation
    advances in `tell`, so a lost evaluation can be re-asked with the same generator.
    """
    if spec_layout.n_weights != state.n_weights:
        raise ValueError(
            f"layout has {spec_layout.n_weights} weights but the state has {state.n_weights}"
        )
    if state.ranked is None:
        return np.ascontiguousarray(initial_population(rng, spec_layout, params)), state
    n, m = params.population, params.replacement
    if state.ranked.shape[0] != n:
        raise ValueError(f"state ranks {state.ranked.shape[0]} genomes but population is {n}")
    elites = state.ranked[:m]
    mutants, _ = mutate(rng, elites, spec_layout, params)
    parts = [elites, mutants, state.ranked[_fill_ranks(params, state.elite_k2 is not None)]]
    if state.elite_k2 is not None:
        parts.append(state.elite_k2[np.newaxis, :])
    return np.ascontiguousarray(np.concatenate(parts, axis=0)), state


def rank(fitness: np.ndarray) -> np.ndarray:
    """Indices fittest first: descending, ties in population order, NaN after everything."""
    values = np.asarray(fitness, dtype=np.float64)
    nan = np.isnan(values)
    # lexsort orders by the last key first (NaN flag), then -fitness; it is stable, so ties
    # keep population order.
    return np.lexsort((np.where(nan, 0.0, -values), nan)).astype(np.int64)


def tell(
    genomes: np.ndarray, fitness: np.ndarray, state: GAState, params: GAParams
) -> tuple[GAState, TellMetrics]:
    """Rank the evaluated generation, keep it for the next `ask`, and move its predecessor's best
    into `elite_k2`; fitness NaN marks a failed evaluation (ranked last, never the winner)."""
    genomes = np.asarray(genomes, dtype=np.float64)
    fitness = np.asarray(fitness, dtype=np.float64)
    n = params.population
    if genomes.shape != (n, state.n_weights):
        raise ValueError(f"genomes have shape {genomes.shape}, expected ({n}, {state.n_weights})")
    if fitness.shape != (n,):
        raise ValueError(f"fitness has shape {fitness.shape}, expected ({n},)")
    order = rank(fitness)
    order.flags.writeable = False
    finite = fitness[np.isfinite(fitness)]
    stats = (
        (float(finite.max()), float(finite.mean()), float(finite.min()))
        if finite.size
        else (float("nan"),) * 3
    )
    metrics = TellMetrics(
        generation=state.generation,
        best=stats[0],
        mean=stats[1],
        worst=stats[2],
        order=order,
        nan_count=int(np.isnan(fitness).sum()),
    )
    new_state = GAState(
        generation=state.generation + 1,
        ranked=genomes[order],
        ranked_fitness=fitness[order],
        elite_k2=None if state.ranked is None else state.ranked[0],
        n_weights=state.n_weights,
    )
    return new_state, metrics


def lineage(params: GAParams, generation: int) -> list[tuple[LineageKind, int]]:
    """(kind, parent rank 0-based in the previous generation) for each index `ask` returns.

    Kinds: 'random' (generation 0), 'elite', 'mutant', 'fill', and 'elite_k2' (rank -1: it is
    the best of two generations back, not a member of the previous ranking).
    """
    if generation < 0:
        raise ValueError(f"generation must be >= 0, got {generation}")
    if generation == 0:
        return [("random", -1)] * params.population
    m = params.replacement
    has_k2 = generation >= 2
    out: list[tuple[LineageKind, int]] = [("elite", i) for i in range(m)]
    out += [("mutant", i) for i in range(m)]
    out += [("fill", int(r)) for r in _fill_ranks(params, has_k2)]
    if has_k2:
        out.append(("elite_k2", -1))
    return out


def ga_rng(seed: int, generation: int) -> np.random.Generator:
    """The generator `ask` takes at `generation`: INIT draws for 0, MUTATION draws after."""
    return rng(seed, generation, Purpose.INIT if generation == 0 else Purpose.MUTATION)
