"""Controller steps per second: compiled `step` vs the numpy reference, two presets, three batches.

Run: .venv/bin/python bench/controller.py   (about 20 s on 2 cores; prints a table, asserts nothing)
A "controller step" is one individual advanced by one time step, so a batch of B counts B.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from evorobotics.network import reset, step, step_reference
from schemas.network import PRESETS, NetworkSpec

StepFn = Callable[[NetworkSpec, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

BUDGET_S = 1.0
"""Wall time spent timing each (preset, batch, path) cell after warm-up."""


def _rate(fn: StepFn, preset: str, batch: int) -> float:
    """Controller steps per second of `fn` over ~BUDGET_S of repeated whole-batch steps."""
    spec = PRESETS[preset]
    rng = np.random.default_rng(0)
    w = rng.normal(scale=0.5, size=(batch, spec.weight_count))
    x = rng.integers(0, 2, size=(batch, spec.inputs)).astype(np.float64)
    state = reset(spec, batch)
    _, state = fn(spec, w, x, state)  # warm-up: JIT load, caches
    calls = 0
    start = time.perf_counter()
    while (elapsed := time.perf_counter() - start) < BUDGET_S:
        _, state = fn(spec, w, x, state)
        calls += 1
    return calls * batch / elapsed


def main() -> None:
    print(f"{'preset':14s} {'weights':>7s} {'batch':>6s} {'compiled/s':>12s} {'numpy/s':>12s}")
    for preset in ("paper-best", "paper-largest"):
        for batch in (1, 256, 4096):
            compiled = _rate(step, preset, batch)
            reference = _rate(step_reference, preset, batch)
            print(
                f"{preset:14s} {PRESETS[preset].weight_count:7d} {batch:6d} "
                f"{compiled:12,.0f} {reference:12,.0f}"
            )


if __name__ == "__main__":
    main()
