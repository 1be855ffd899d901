"""Controller steps per second: `step` (specialised kernel), generic `step_one`, numpy reference.

Run: .venv/bin/python bench/controller.py   (about 30 s on 2 cores; prints a table, asserts nothing)
A "controller step" is one individual advanced by one time step, so a batch of B counts B.
Also prints the first `step` of a fresh process per preset, with a cold kernel cache (a new
temporary EVOCOLONY_KERNEL_CACHE: generate and compile) and a warm one (load machine code).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable

import numpy as np
from numba import njit

from evorobotics.network import kernel_plan, reset, scratch_size, step, step_one, step_reference
from schemas.network import PRESETS, NetworkSpec

StepFn = Callable[[NetworkSpec, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

BUDGET_S = 1.0
"""Wall time spent timing each (preset, batch, path) cell after warm-up."""


@njit(cache=True)
def _generic_batch(
    weights: np.ndarray,
    sizes: np.ndarray,
    hist_off: np.ndarray,
    act_off: np.ndarray,
    blocks: np.ndarray,
    delays: int,
    linear_output: int,
    state: np.ndarray,
    inputs: np.ndarray,
    out: np.ndarray,
    scratch: np.ndarray,
) -> None:
    for r in range(weights.shape[0]):
        step_one(
            weights[r],
            sizes,
            hist_off,
            act_off,
            blocks,
            delays,
            linear_output,
            state[r],
            inputs[r],
            out[r],
            scratch,
        )


def generic_step(
    spec: NetworkSpec, weights: np.ndarray, inputs: np.ndarray, state: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """`step` through the generic `step_one` (the kernel before specialisation), same results."""
    new_state = state.copy()
    out = np.empty((weights.shape[0], spec.outputs))
    scratch = np.empty(scratch_size(spec))
    _generic_batch(weights, *kernel_plan(spec), new_state, inputs, out, scratch)
    return out, new_state


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


FIRST_STEP = """
import sys, time
import numpy as np
from evorobotics.network import reset, step
from schemas.network import PRESETS
spec = PRESETS[sys.argv[1]]
t0 = time.perf_counter()
step(spec, np.zeros((1, spec.weight_count)), np.zeros((1, spec.inputs)), reset(spec, 1))
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
    for preset in ("paper-best", "paper-largest"):
        with tempfile.TemporaryDirectory() as cache:
            cold = first_call_seconds(FIRST_STEP, preset, cache)
            warm = first_call_seconds(FIRST_STEP, preset, cache)
        print(f"{preset}: first step() of a process, cold cache {cold:.2f} s, warm {warm:.2f} s")
    print(
        f"{'preset':14s} {'weights':>7s} {'batch':>6s} {'step/s':>12s} "
        f"{'step_one/s':>12s} {'numpy/s':>12s}"
    )
    for preset in ("paper-best", "paper-largest"):
        for batch in (1, 256, 4096):
            compiled = _rate(step, preset, batch)
            generic = _rate(generic_step, preset, batch)
            reference = _rate(step_reference, preset, batch)
            print(
                f"{preset:14s} {PRESETS[preset].weight_count:7d} {batch:6d} "
                f"{compiled:12,.0f} {generic:12,.0f} {reference:12,.0f}"
            )


if __name__ == "__main__":
    main()
