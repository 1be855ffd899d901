"""Simulator speed: robot-steps per second per core of the tiled kernel against the one-robot
kernel it replaced (bench/_old_kernel.py), interleaved in one run, as a fraction of the core's
measured FP64 peak; then the numpy reference, first-call compile times and evaluate().

Run: .venv/bin/python bench/sim.py [--kernel-only] [--against DIR [--rounds R]]. Best of
several repeats (the machine may be shared); one core (the kernel is single-threaded). Random
genomes, 40-step trials in the "paper" maze from the evaluation's own start poses.

With `--against DIR` (a checkout of another commit, e.g. main's) the tiled kernel's rows
(batch 1024, both worlds, both presets) are also measured in fresh processes from this tree
and from DIR in turn, R rounds (default 5): the median of each tree's rounds and their ratio,
with the load average before and after.

Two kinds of rows. "default world": a robot that gets stuck (paper rule, stuck_after = 1) stops
and its remaining steps are skipped (counted as robot-steps all the same), so the figure
depends on how many robots get stuck. "never stuck": World(stuck_after=10**6), so every robot
runs all 40 steps (controller, physics and collision each step; a robot blocked against a wall
keeps its whisker bits and its blocked pose's test result, as the kernel does in any world),
the honest cost of a robot-step.

Peak: a loop of independent FP64 fused multiply-adds on 8-lane vectors, as many as the core
retires (`fma_peak`). The fraction of peak counts 2 flops per weight (multiply, add) and 143
for the geometry (whiskers, move, collision) per robot-step.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from _old_kernel import simulate_old
from llvmlite import ir as llvm_ir
from numba import njit, types
from numba.core import cgutils as _cgutils
from numba.extending import intrinsic

from evorobotics.evaluate import evaluate, start_poses, trial_steps
from evorobotics.evolution import evolve
from evorobotics.maze import load_maze
from evorobotics.sim import DEFAULT_WORLD, simulate, simulate_reference
from schemas.network import PRESETS
from schemas.run import RunConfig
from schemas.world import World

STEPS = 40
NEVER_STUCK = World(stuck_after=10**6)
GEOMETRY_FLOPS = 143
cgutils: Any = _cgutils
"""numba's codegen helpers, untyped."""

CHAINS = 16
"""Independent accumulators of the peak loop: enough to hide the FMA latency on two units."""


def _fma_chains_typer(typingctx: object, n: types.Integer) -> tuple[Any, Callable[..., object]]:
    """n rounds of CHAINS independent 8-lane FP64 FMAs (acc = acc * a + b); the lanes' sum."""

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> object:
        vec = llvm_ir.VectorType(llvm_ir.DoubleType(), 8)
        fma = cgutils.get_or_insert_function(
            builder.module, llvm_ir.FunctionType(vec, [vec, vec, vec]), "llvm.fma.v8f64"
        )
        a = llvm_ir.Constant(vec, [0.999999] * 8)
        b = llvm_ir.Constant(vec, [1e-6] * 8)
        accs = [
            cgutils.alloca_once_value(builder, llvm_ir.Constant(vec, [float(k)] * 8))
            for k in range(CHAINS)
        ]
        count = context.cast(builder, args[0], signature.args[0], types.intp)
        with cgutils.for_range(builder, count):
            for acc in accs:
                builder.store(builder.call(fma, [builder.load(acc), a, b]), acc)
        total = builder.load(accs[0])
        for acc in accs[1:]:
            total = builder.fadd(total, builder.load(acc))
        return builder.extract_element(total, llvm_ir.Constant(llvm_ir.IntType(32), 0))

    return types.float64(n), codegen


_fma_chains: Any = intrinsic(_fma_chains_typer)


def _peak_loop_py(n: int) -> float:
    return float(_fma_chains(n))


_peak_loop: Any = njit(_peak_loop_py)


def fma_peak() -> float:
    """The core's FP64 peak in flop/s, measured: best of repeats of the FMA loop."""
    rounds = 2_000_000
    seconds = best_of(lambda: _peak_loop(rounds), 5)
    return rounds * CHAINS * 8 * 2 / seconds


def best_of(fn: Callable[[], object], repeats: int) -> float:
    """Shortest wall time of `repeats` calls, after one warm-up call (compilation)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def interleaved(fns: list[Callable[[], object]], repeats: int) -> list[float]:
    """Shortest wall time of each function, called in turn (A, B, A, B, ...) after a warm-up."""
    for fn in fns:
        fn()
    best = [float("inf")] * len(fns)
    for _ in range(repeats):
        for i, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            best[i] = min(best[i], time.perf_counter() - t0)
    return best


def compare(preset: str, batch: int, params: World) -> tuple[float, float, float]:
    """(old robot-steps/s, new robot-steps/s, fraction of robots that ended stuck)."""
    spec = PRESETS[preset]
    maze = load_maze("paper")
    weights = np.random.default_rng(0).normal(0.0, 1.5, (batch, spec.weight_count))
    starts = np.resize(start_poses(maze, 0, 0, 64), (batch, 3))
    work = batch * STEPS * spec.weight_count
    repeats = max(3, min(200, 4_000_000 // work))
    old, new = interleaved(
        [
            lambda: simulate_old(spec, weights, maze, starts, STEPS, params),
            lambda: simulate(spec, weights, maze, starts, STEPS, params),
        ],
        repeats,
    )
    stuck = float(simulate(spec, weights, maze, starts, STEPS, params).stuck.mean())
    return batch * STEPS / old, batch * STEPS / new, stuck


def reference_rate(params: World) -> float:
    spec = PRESETS["paper-best"]
    maze = load_maze("paper")
    weights = np.random.default_rng(0).normal(0.0, 1.5, (1024, spec.weight_count))
    starts = np.resize(start_poses(maze, 0, 0, 64), (1024, 3))
    seconds = best_of(lambda: simulate_reference(spec, weights, maze, starts, STEPS, params), 3)
    return 1024 * STEPS / seconds


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


KERNEL_RATES = """
import json, sys, time
import numpy as np
from evorobotics.evaluate import start_poses
from evorobotics.maze import load_maze
from evorobotics.sim import simulate
from schemas.network import PRESETS
from schemas.world import World
maze, rates = load_maze("paper"), {}
starts = np.resize(start_poses(maze, 0, 0, 64), (1024, 3))
for world in ("default", "never stuck"):
    params = World() if world == "default" else World(stuck_after=10**6)
    for preset in ("paper-best", "paper-largest"):
        spec = PRESETS[preset]
        weights = np.random.default_rng(0).normal(0.0, 1.5, (1024, spec.weight_count))
        simulate(spec, weights, maze, starts, 40, params)
        best = float("inf")
        for _ in range(max(3, 4_000_000 // (1024 * 40 * spec.weight_count))):
            t0 = time.perf_counter()
            simulate(spec, weights, maze, starts, 40, params)
            best = min(best, time.perf_counter() - t0)
        rates[f"{world}, {preset}"] = 1024 * 40 / best
print(json.dumps(rates))
"""
"""Robot-steps/s of the tiled kernel, batch 1024, in a fresh process, as JSON."""


def load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def against(tree: Path, rounds: int) -> None:
    """KERNEL_RATES from this tree and from `tree` in turn: medians of rounds, ratios."""
    root = Path(__file__).resolve().parents[1]
    trees = {"this tree": root, str(tree): tree}
    print(f"tiled kernel, batch 1024, {STEPS}-step trials, this tree against {tree}, fresh")
    print(f"processes in turn, median of {rounds} rounds (load average {load()} before):")
    found: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    with tempfile.TemporaryDirectory() as cwd:  # off any checkout: `-c` puts cwd on the path
        for i in range(rounds + 1):  # the first round warms the kernel caches
            for name, path in trees.items():
                done = subprocess.run(
                    [sys.executable, "-c", KERNEL_RATES],
                    env={**os.environ, "PYTHONPATH": str(path)},
                    cwd=cwd,
                    capture_output=True,
                    text=True,
                    check=True,
                )
                if i:
                    found[name].append(json.loads(done.stdout.splitlines()[-1]))
    mine, other = found.values()
    for row in mine[0]:
        a = statistics.median(r[row] for r in mine)
        b = statistics.median(r[row] for r in other)
        print(f"  {row:28s} this tree {a / 1e6:7.3f} M/s  {tree}: {b / 1e6:7.3f} M/s  x{a / b:.2f}")
    print(f"  (load average {load()} after)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kernel-only", action="store_true", help="skip evaluate() and evolve")
    parser.add_argument("--against", type=Path, help="a checkout of another commit to compare")
    parser.add_argument("--rounds", type=int, default=5, help="--against: interleaved rounds")
    args = parser.parse_args()
    if args.against is not None:
        against(args.against, args.rounds)
    peak = fma_peak()
    print(f"FP64 peak of one core (FMA loop): {peak / 1e9:.1f} GFLOP/s")
    print(
        f"robot-steps/s per core, {STEPS}-step trials in the 'paper' maze, one-robot kernel "
        "against the tiled one, interleaved (best of repeats)"
    )
    for label, params in (("default world", DEFAULT_WORLD), ("never stuck", NEVER_STUCK)):
        print(f" {label} (stuck_after={params.stuck_after}):")
        for preset in ("paper-best", "paper-largest"):
            flops = 2 * PRESETS[preset].weight_count + GEOMETRY_FLOPS
            for batch in (1, 256, 1024, 4096):
                old, new, stuck = compare(preset, batch, params)
                print(
                    f"  {preset:14s} batch {batch:5d}: old {old / 1e6:7.3f} M/s  "
                    f"tiled {new / 1e6:7.3f} M/s  x{new / old:5.2f}  "
                    f"{100 * new * flops / peak:5.2f} % of peak  stuck {stuck:.2f}"
                )
        ref = reference_rate(params)
        print(f"  numpy reference paper-best batch  1024: {ref / 1e6:7.3f} M/s")
    for preset in ("paper-best", "paper-largest"):
        with tempfile.TemporaryDirectory() as cache:
            cold = first_call_seconds(FIRST_SIMULATE, preset, cache)
            warm = first_call_seconds(FIRST_SIMULATE, preset, cache)
        print(
            f" first simulate() of {preset} in a process: cold cache {cold:.2f} s, warm {warm:.2f} s"
        )
    if not args.kernel_only:
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
