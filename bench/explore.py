"""Does the evolved controller actually explore? Evolved vs reactive vs random, on unseen poses.

Evolves the paper's default experiment (paper-best: time-delayed, 222 weights) and the same
experiment with the purely reactive network (218 weights), draws the random Eq 7 population of
paper-best, then evaluates the best of each evolved run and every random controller over the
SAME 100 start poses, never seen in training (start_poses(maze, seed=12345, generation=0,
trials=100)), for 40 and for 200 steps. Prints mean fitness, mean max offset and stuck fraction.

Run: .venv/bin/python bench/explore.py [--generations N] [--seed S]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from evorobotics.evaluate import evaluate
from evorobotics.evolution import RunLoop, evolve
from schemas.run import RunConfig

TEST_SEED = 12345
TEST_TRIALS = 100


def unseen(config: RunConfig, genomes: np.ndarray, steps: int) -> tuple[float, float, float]:
    """Mean fitness, mean max offset (m) and stuck fraction over the shared unseen poses.

    evaluate() at generation 0 with seed TEST_SEED and TEST_TRIALS trials draws exactly
    start_poses(maze, TEST_SEED, 0, TEST_TRIALS), the same poses for every controller.
    """
    test = config.model_copy(update={"seed": TEST_SEED, "trials": TEST_TRIALS, "steps": steps})
    ev = evaluate(test, 0, genomes)
    return (
        float(np.mean(ev.fitness)),
        float(np.mean(ev.components[..., 2])),
        float(np.mean(ev.components[..., 3] > 0)),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generations", type=int, default=RunConfig().generations)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    base = RunConfig(generations=args.generations, seed=args.seed)
    rows: list[tuple[str, int, tuple[float, float, float]]] = []
    for label, network in (("evolved paper-best", "paper-best"), ("evolved reactive", "reactive")):
        config = base.model_copy(update={"network": network})
        t0 = time.perf_counter()
        result = evolve(config)
        print(
            f"{label}: {config.generations} generations in {time.perf_counter() - t0:.1f} s, "
            f"training fitness {result.best.fitness:.3f}"
        )
        best = np.asarray(result.best.weights)[None, :]
        for steps in (40, 200):
            rows.append((label, steps, unseen(config, best, steps)))

    random_genomes = RunLoop(base).ask()  # generation 0: the Eq 7 population
    for steps in (40, 200):
        rows.append(
            (
                f"random paper-best x{len(random_genomes)}",
                steps,
                unseen(base, random_genomes, steps),
            )
        )

    print()
    print(
        f"unseen start poses: start_poses(maze={base.maze!r}, seed={TEST_SEED}, generation=0, "
        f"trials={TEST_TRIALS})"
    )
    print(f"{'controller':28s} {'steps':>5s} {'fitness':>9s} {'max offset m':>13s} {'stuck':>6s}")
    for label, steps, (fit, off, stuck) in rows:
        print(f"{label:28s} {steps:5d} {fit:9.3f} {off:13.3f} {stuck:6.2f}")


if __name__ == "__main__":
    main()
