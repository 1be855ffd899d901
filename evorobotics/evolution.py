"""Local evolution: the run loop every role composes identically, and the job slices.

An individual's fitness depends on the config, the generation and its own genome only (trial
conditions are drawn per generation, robots are independent), never on which other genomes
share its `evaluate` call. So how a generation is cut into contiguous jobs (`job_slices`; the
server cuts by the run's `job_size` or, with zenoh workers, one job per live worker) cannot
change a run, and `evolve` evaluates the whole generation in one call: bit-identical fitness
arrays either way.
`best_document` names the best controller the same way for `colony evolve` and the server
(rank 0 of the latest completed generation).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from evorobotics.document import ControllerDocument
from evorobotics.evaluate import evaluate
from evorobotics.ga import GAParams, GAState, ask, ga_rng, init, tell
from evorobotics.layout import layout
from schemas.run import RunConfig


def job_slices(population: int, job_size: int) -> list[tuple[int, int]]:
    """Contiguous [start, stop) slices of `job_size` covering 0..population, in order."""
    if population < 1:
        raise ValueError(f"population must be >= 1, got {population}")
    if job_size < 1:
        raise ValueError(f"job_size must be >= 1, got {job_size}")
    return [(a, min(a + job_size, population)) for a in range(0, population, job_size)]


@dataclass(frozen=True)
class GenerationSummary:
    """One completed generation's fitness statistics (over finite values; NaN if none)."""

    generation: int
    best: float
    mean: float
    worst: float
    nan_count: int


@dataclass(frozen=True)
class EvolutionResult:
    """Everything a finished local run produced; arrays are those of the last generation."""

    state: GAState
    history: tuple[GenerationSummary, ...]
    best: ControllerDocument
    genomes: np.ndarray
    """(population, n_weights) the last generation evaluated, in ask() order."""
    fitness: np.ndarray
    """(population,) Eq 12 fitness of `genomes`."""
    components: np.ndarray
    """(population, trials, 4) per-trial (curve_length, net_offset, max_offset, stuck)."""


def best_document(
    config: RunConfig,
    genomes: np.ndarray,
    fitness: np.ndarray,
    order: np.ndarray,
    *,
    generation: int,
    run: str | int = "local",
) -> ControllerDocument:
    """The controller document of rank 0 (`order[0]`) of a completed generation.

    `order` is the ranking from `tell` (TellMetrics.order); a caller holding genomes already
    sorted fittest first passes `np.arange(n)`. The provenance says where it came from.
    """
    genomes = np.asarray(genomes)
    fitness = np.asarray(fitness)
    if genomes.ndim != 2 or fitness.shape != (genomes.shape[0],):
        raise ValueError(
            f"genomes must be (n, w) with fitness (n,), got {genomes.shape} and {fitness.shape}"
        )
    if len(order) == 0:
        raise ValueError("order is empty: no individual to choose")
    if generation < 0:
        raise ValueError(f"generation must be >= 0, got {generation}")
    top = int(order[0])
    value = float(fitness[top])
    return ControllerDocument(
        spec=config.network_spec,
        weights=np.array(genomes[top], dtype=np.float64),
        fitness=value if np.isfinite(value) else None,
        provenance={"seed": config.seed, "generation": generation, "rank": 0, "run": run},
    )


def evaluate_population(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Fitness (n,) and components (n, trials, 4) of a generation's n = population genomes.

    One `evaluate` call for the whole population: bit-identical to evaluating it job by job in
    `job_slices` and concatenating (property-tested), without the per-call cost of each job.
    """
    genomes = np.asarray(genomes)
    if genomes.ndim != 2 or genomes.shape[0] != config.population:
        raise ValueError(
            f"genomes must be ({config.population}, n_weights), one row per individual, "
            f"got {genomes.shape}"
        )
    result = evaluate(config, generation, genomes)
    return result.fitness, result.components


def evolve(
    config: RunConfig,
    *,
    on_generation: Callable[[GenerationSummary], None] | None = None,
) -> EvolutionResult:
    """Run the whole experiment of `config` in this process; a pure function of the config."""
    lay = layout(config.network_spec)
    params = GAParams.from_config(config)
    state = init(lay, params)
    history: list[GenerationSummary] = []
    genomes = fitness = components = order = np.empty(0)
    for g in range(config.generations):
        genomes, state = ask(ga_rng(config.seed, g), state, params, lay)
        fitness, components = evaluate_population(config, g, genomes)
        state, metrics = tell(genomes, fitness, state, params)
        order = metrics.order
        summary = GenerationSummary(g, metrics.best, metrics.mean, metrics.worst, metrics.nan_count)
        history.append(summary)
        if on_generation is not None:
            on_generation(summary)
    best = best_document(
        config, genomes, fitness, order, generation=config.generations - 1, run="local"
    )
    return EvolutionResult(state, tuple(history), best, genomes, fitness, components)
