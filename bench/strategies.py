"""Strategy overhead: ask + tell per generation (no evaluation) against the simulation it drives.

Run: .venv/bin/python bench/strategies.py [--rounds N] [--generations G]. At the paper's scale
(population 100, paper-best: 222 weights, 3 trials of the default length): paper-ga, cma-es,
map-elites (and cma-me, novelty besides); sep-cma-es on paper-largest (7,104 weights). Each
round times G generations of ask + tell per strategy (fitness and descriptors from one real
evaluation, reused), then one real evaluation of a generation per network: strategies and
simulation interleaved, medians over rounds. The simulation is of a population evolved for
EVOLVED generations by the paper GA (random genomes get stuck early and are unrepresentatively
cheap). Last, the time `RunLoop.resume` takes to replay 350 generations of each strategy.
Target (issue 26): overhead <= 10 % of the simulation for paper-ga, cma-es and map-elites.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from evorobotics.evaluate import evaluate
from evorobotics.evolution import RunLoop, StrategyHistory, evolve
from schemas.run import RunConfig, StrategyName

EVOLVED = 30
"""Generations of the paper GA behind the population whose evaluation is timed."""

ROWS: tuple[tuple[StrategyName, str], ...] = (
    ("paper-ga", "paper-best"),
    ("cma-es", "paper-best"),
    ("map-elites", "paper-best"),
    ("cma-me", "paper-best"),
    ("novelty", "paper-best"),
    ("sep-cma-es", "paper-best"),
    ("sep-cma-es", "paper-largest"),
)


def evolved_population(network: str) -> np.ndarray:
    return evolve(RunConfig(network=network, generations=EVOLVED)).genomes


def overhead(loop: RunLoop, told: tuple[np.ndarray, np.ndarray, np.ndarray], g: int) -> float:
    """Seconds per generation of ask + tell over `g` generations of `loop`."""
    fitness, components, descriptors = told
    t0 = time.perf_counter()
    for _ in range(g):
        loop.ask()
        loop.tell(fitness, components, descriptors)
    return (time.perf_counter() - t0) / g


def replay_seconds(config: RunConfig, told: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
    n = 350
    history = StrategyHistory(np.tile(told[0], (n, 1)), np.tile(told[2], (n, 1, 1)))
    t0 = time.perf_counter()
    RunLoop.resume(config.model_copy(update={"generations": n}), history)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--generations", type=int, default=10, help="ask+tell per round")
    parser.add_argument("--population", type=int, default=100)
    args = parser.parse_args()
    pops = {net: evolved_population(net) for net in {net for _, net in ROWS}}
    configs = {
        (s, net): RunConfig(strategy=s, network=net, population=args.population, generations=10**5)
        for s, net in ROWS
    }
    pops = {net: np.resize(p, (args.population, p.shape[1])) for net, p in pops.items()}
    told = {}
    for net, pop in pops.items():
        ev = evaluate(RunConfig(network=net), 1, pop)
        told[net] = (ev.fitness, ev.components, ev.descriptors)
    loops = {key: RunLoop(c) for key, c in configs.items()}
    for key, loop in loops.items():  # warm up: imports, first generation
        overhead(loop, told[key[1]], 1)
    per_gen: dict[tuple[StrategyName, str], list[float]] = {key: [] for key in loops}
    sim: dict[str, list[float]] = {net: [] for net in pops}
    generation = 1
    for _ in range(args.rounds):
        for key, loop in loops.items():
            per_gen[key].append(overhead(loop, told[key[1]], args.generations))
        for net, pop in pops.items():
            generation += 1  # new trial conditions each time, as a run meets them
            t0 = time.perf_counter()
            evaluate(RunConfig(network=net), generation, pop)
            sim[net].append(time.perf_counter() - t0)
    print(
        f"population {args.population}, {args.rounds} rounds x {args.generations} generations "
        f"of ask+tell (medians); simulation: one generation of an evolved population"
    )
    for net in pops:
        print(f"  simulation {net:14s}: {statistics.median(sim[net]) * 1e3:8.2f} ms/generation")
    for (s, net), values in per_gen.items():
        o = statistics.median(values)
        ratio = o / statistics.median(sim[net])
        print(
            f"  {s:11s} {net:14s}: ask+tell {o * 1e3:8.3f} ms/generation = "
            f"{ratio:6.1%} of the simulation"
        )
    print("replay of 350 generations (RunLoop.resume, no evaluation):")
    for (s, net), config in configs.items():
        print(f"  {s:11s} {net:14s}: {replay_seconds(config, told[net]):.2f} s")


if __name__ == "__main__":
    main()
