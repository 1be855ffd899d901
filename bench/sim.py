"""Simulator speed: robot-steps per second of the fused kernel, the numpy reference and evaluate().

Run: .venv/bin/python bench/sim.py. Best of several repeats (the machine may be shared); one
core (the kernel is single-threaded). Random genomes, 40-step trials in the "paper" maze from
the evaluation's own start poses.

Two kinds of rows. "default world": a robot that gets stuck (paper rule, stuck_after = 1) stops
and its remaining steps are skipped, so the figure depends on how many robots get stuck.
"never stuck": World(stuck_after=10**6), so every robot runs all 40 steps (controller,
whiskers, physics, collision test each step), the honest cost of a robot-step and the figure
the target (2 M robot-steps/s at batch >= 1024 for paper-best) is judged on.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial

import numpy as np

from evorobotics.evaluate import evaluate, start_poses, trial_steps
from evorobotics.evolution import evolve
from evorobotics.maze import load_maze
from evorobotics.sim import DEFAULT_WORLD, simulate, simulate_reference
from schemas.network import PRESETS
from schemas.run import RunConfig
from schemas.world import World

STEPS = 40
NEVER_STUCK = World(stuck_after=10**6)


def best_of(fn: Callable[[], object], repeats: int) -> float:
    """Shortest wall time of `repeats` calls, after one warm-up call (compilation)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def rate(preset: str, batch: int, params: World, reference: bool = False) -> tuple[float, float]:
    """(robot-steps per second, fraction of robots that ended stuck)."""
    spec = PRESETS[preset]
    maze = load_maze("paper")
    weights = np.random.default_rng(0).normal(0.0, 1.5, (batch, spec.weight_count))
    starts = np.resize(start_poses(maze, 0, 0, 64), (batch, 3))
    run = simulate_reference if reference else simulate
    repeats = 3 if reference else max(3, 20_000 // batch)
    seconds = best_of(lambda: run(spec, weights, maze, starts, STEPS, params), repeats)
    stuck = float(run(spec, weights, maze, starts, STEPS, params).stuck.mean())
    return batch * STEPS / seconds, stuck


FIRST_SIMULATE = """
import sys, time
import numpy as np
from evorobotics.evaluate import start_poses
from evorobotics.maze import load_maze
from evorobotics.sim import simulate
from schemas.network import PRESETS
spec, maze = PRESETS[sys.argv[1]], load_maze("paper")
t0 = time.perf_counter()
simulate(spec, np.zeros((1, spec.weight_count)), maze, start_poses(maze, 0, 0, 1), 1)
print(time.perf_counter() - t0)
"""


def first_call_seconds(script: str, preset: str, cache: str) -> float:
    """Seconds of the timed first call in `script`, run by a fresh interpreter using `cache`."""
    env = {**os.environ, "EVOCOLONY_KERNEL_CACHE": cache}
    done = subprocess.run(
        [sys.executable, "-c", script, preset], env=env, capture_output=True, text=True, check=True
    )
    return float(done.stdout.split()[-1])


def main() -> None:
    print(f"robot-steps/s, {STEPS}-step trials in the 'paper' maze (best of repeats, one core)")
    rows = [
        ("paper-best", 1),
        ("paper-best", 256),
        ("paper-best", 1024),
        ("paper-best", 4096),
        ("paper-largest", 1024),
    ]
    for preset in ("paper-best", "paper-largest"):
        with tempfile.TemporaryDirectory() as cache:
            cold = first_call_seconds(FIRST_SIMULATE, preset, cache)
            warm = first_call_seconds(FIRST_SIMULATE, preset, cache)
        print(
            f" first simulate() of {preset} in a process: cold cache {cold:.2f} s, warm {warm:.2f} s"
        )
    for label, params in (("default world", DEFAULT_WORLD), ("never stuck", NEVER_STUCK)):
        print(f" {label} (stuck_after={params.stuck_after}):")
        for preset, batch in rows:
            r, stuck = rate(preset, batch, params)
            print(
                f"  kernel     {preset:14s} batch {batch:5d}: {r / 1e6:7.3f} M/s  stuck {stuck:.2f}"
            )
        r, stuck = rate("paper-best", 1024, params, True)
        print(f"  reference  paper-best     batch  1024: {r / 1e6:7.3f} M/s  stuck {stuck:.2f}")
    evaluate_calls()


def each_call_a_new_generation(config: RunConfig, genomes: np.ndarray) -> Callable[[], object]:
    """evaluate() as a worker meets it: new trial conditions, so start poses are drawn anew."""
    generations = iter(range(1, 10**6))
    return lambda: evaluate(config, next(generations), genomes)


def evaluate_calls() -> None:
    """evaluate() per call, paper config, on an evolved population (random genomes get stuck
    early, so they are unrepresentatively fast); then the whole default run."""
    config = RunConfig()
    pop = evolve(RunConfig(generations=50)).genomes
    print(
        f"evaluate() calls, default config, population of generation 50 ({config.trials} trials "
        f"of {trial_steps(config)} steps):"
    )
    for k in (1, 25, config.population):
        seconds = best_of(partial(evaluate, config, 7, pop[:k]), max(20, 2000 // k))
        robots = k * config.trials
        print(
            f"  {k:3d} individuals, same generation (cached draws): {seconds * 1e3:6.3f} ms "
            f"= {robots * trial_steps(config) / seconds / 1e6:.3f} M robot-steps/s"
        )
    for k in (1, 25):
        seconds = best_of(each_call_a_new_generation(config, pop[:k]), 200)
        print(f"  {k:3d} individuals, a new generation each call:     {seconds * 1e3:6.3f} ms")
    seconds = best_of(lambda: evolve(RunConfig()), 3)
    print(f"evolve(RunConfig()): {seconds:.2f} s ({config.generations} generations)")


if __name__ == "__main__":
    main()
