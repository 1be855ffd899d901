"""The controller network (Eqs 1-6, 8): compiled path, numpy reference, state and semantics."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
import types
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from evorobotics.layout import layout
from evorobotics.network import (
    CACHE_ENV,
    LANES,
    LINEAR_BOUND,
    _exp_neg,
    _sigmoid,
    _sigmoid_rows,
    cached_module,
    kernel_cache_dir,
    kernel_plan,
    motor_commands,
    motor_one,
    reset,
    scratch_size,
    spec_kernel,
    state_size,
    step,
    step_one,
    step_reference,
)
from schemas.network import PRESETS, NetworkSpec

StepFn = Callable[[NetworkSpec, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@st.composite
def specs(draw: st.DrawFn, max_hidden: int = 3, max_delays: int = 3) -> NetworkSpec:
    """Random small specs: hidden 0..3 layers, T 0..3, S 0..M or per-layer depths, both
    output activations."""
    hidden = tuple(draw(st.lists(st.integers(1, 5), max_size=max_hidden)))
    layers = len(hidden) + 1
    per_layer = st.tuples(*(st.integers(0, layers - m + 1) for m in range(1, layers + 1)))
    return NetworkSpec(
        inputs=draw(st.integers(1, 5)),
        hidden=hidden,
        outputs=draw(st.integers(1, 3)),
        output_activation=draw(st.sampled_from(["sigmoid", "linear"])),
        delays=draw(st.integers(0, max_delays)),
        recurrence=draw(st.one_of(st.integers(0, layers), per_layer)),
    )


POOL = (
    NetworkSpec(inputs=1, hidden=(), outputs=1, delays=0, recurrence=0),
    NetworkSpec(inputs=3, hidden=(), outputs=2, delays=1, recurrence=0),
    NetworkSpec(inputs=2, hidden=(), outputs=3, output_activation="linear", delays=2, recurrence=1),
    NetworkSpec(inputs=2, hidden=(), outputs=3, output_activation="linear", delays=0, recurrence=0),
    NetworkSpec(inputs=3, hidden=(4,), outputs=2, delays=1, recurrence=2),
    NetworkSpec(inputs=3, hidden=(4,), outputs=2, delays=0, recurrence=0),
    NetworkSpec(
        inputs=5, hidden=(2, 3), outputs=1, output_activation="linear", delays=3, recurrence=1
    ),
    NetworkSpec(
        inputs=5, hidden=(2, 3), outputs=1, output_activation="linear", delays=0, recurrence=0
    ),
    NetworkSpec(inputs=4, hidden=(3, 1, 2), outputs=2, delays=2, recurrence=4),
    NetworkSpec(inputs=4, hidden=(3, 1, 2), outputs=2, delays=0, recurrence=0),
    NetworkSpec(inputs=2, hidden=(1, 4, 2), outputs=1, output_activation="linear", delays=3),
    NetworkSpec(
        inputs=3,
        hidden=(4, 2),
        outputs=2,
        output_activation="linear",
        delays=1,
        recurrence=(2, 0, 1),
    ),
    PRESETS["paper-best"],
)
"""Specs for the property tests of the canonical `step`. Each spec compiles its own kernel
(~0.5 s), so they draw from this pool (every shape of the `specs()` space: 0-3 hidden layers,
T 0-3, S 0-M or per layer, both activations; most T=0, S=0 twins are here for the zero-weight
test), and `test_spec_kernel_is_step_one_bit_for_bit` carries the result to any spec."""


def _run(
    spec: NetworkSpec, weights: np.ndarray, inputs: np.ndarray, *, reference: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Outputs (steps, B, outputs) and final state of a whole input sequence (steps, B, inputs)."""
    fn = step_reference if reference else step
    state = reset(spec, weights.shape[0])
    outs = []
    for x in inputs:
        out, state = fn(spec, weights, x, state)
        outs.append(out)
    return np.stack(outs), state


def _sequence(rng: np.random.Generator, steps: int, batch: int, spec: NetworkSpec) -> np.ndarray:
    return rng.integers(0, 2, size=(steps, batch, spec.inputs)).astype(np.float64)


@settings(max_examples=40, deadline=None)
@given(spec=st.sampled_from(POOL), seed=st.integers(0, 2**32 - 1), batch=st.integers(1, 6))
def test_compiled_agrees_with_reference(spec: NetworkSpec, seed: int, batch: int) -> None:
    rng = np.random.default_rng(seed)
    w = rng.normal(scale=0.7, size=(batch, spec.weight_count))
    xs = _sequence(rng, 6, batch, spec)
    out_c, state_c = _run(spec, w, xs)
    out_r, state_r = _run(spec, w, xs, reference=True)
    np.testing.assert_allclose(out_c, out_r, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(state_c, state_r, rtol=1e-12, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(spec=st.sampled_from(POOL), seed=st.integers(0, 2**32 - 1), batch=st.integers(2, 9))
def test_batch_equals_single_rows_bit_for_bit(spec: NetworkSpec, seed: int, batch: int) -> None:
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(batch, spec.weight_count))
    xs = _sequence(rng, 5, batch, spec)
    out_b, state_b = _run(spec, w, xs)
    for r in range(batch):
        out_r, state_r = _run(spec, w[r : r + 1], xs[:, r : r + 1])
        assert np.array_equal(out_b[:, r], out_r[:, 0])
        assert np.array_equal(state_b[r], state_r[0])


@settings(max_examples=30, deadline=None)
@given(spec=st.sampled_from(POOL), seed=st.integers(0, 2**32 - 1))
def test_zero_weights_are_absent_connections(spec: NetworkSpec, seed: int) -> None:
    """Zero delayed and recurrent blocks give exactly the outputs of the T=0, S=0 network."""
    rng = np.random.default_rng(seed)
    lay = layout(spec)
    plain = spec.model_copy(update={"delays": 0, "recurrence": 0})
    w = np.zeros((2, spec.weight_count))
    kept = []
    for blk in lay.blocks:
        if blk.t == 0 and blk.s == 0:
            sl = slice(blk.offset, blk.offset + blk.size)
            w[:, sl] = rng.normal(size=(2, blk.size))
            kept.append(w[:, sl])
    w_plain = np.concatenate(kept, axis=1)
    assert w_plain.shape[1] == plain.weight_count
    xs = _sequence(rng, 6, 2, spec)
    out_full, _ = _run(spec, w, xs)
    out_plain, _ = _run(plain, w_plain, xs)
    assert np.array_equal(out_full, out_plain)


@settings(max_examples=30, deadline=None)
@given(
    spec=st.sampled_from([p for p in POOL if p.delays >= 1 and p.recurrence == 0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_delayed_network_sees_exactly_m_times_t_steps_back(spec: NetworkSpec, seed: int) -> None:
    horizon = spec.layers * spec.delays
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(1, spec.weight_count))
    steps = horizon + 3
    xs = rng.normal(size=(steps, 1, spec.inputs))
    base, _ = _run(spec, w, xs)
    last = steps - 1
    at_horizon = xs.copy()
    at_horizon[last - horizon] += 1.0
    changed, _ = _run(spec, w, at_horizon)
    assert not np.array_equal(changed[last], base[last])
    for earlier in range(last - horizon):
        before = xs.copy()
        before[earlier] += 1.0
        same, _ = _run(spec, w, before)
        assert np.array_equal(same[last], base[last])


def test_reactive_network_forgets_at_once_and_reset_is_zero() -> None:
    spec = PRESETS["reactive"]
    rng = np.random.default_rng(1)
    w = rng.normal(size=(3, spec.weight_count))
    state = reset(spec, 3)
    assert state.shape == (3, state_size(spec)) and not state.any()
    x = np.ones((3, spec.inputs))
    first, state = step(spec, w, x, state)
    again, _ = step(spec, w, x, state)
    assert np.array_equal(first, again)


def test_recurrent_network_remembers() -> None:
    spec = PRESETS["recurrent-small"]
    w = np.random.default_rng(2).normal(size=(1, spec.weight_count))
    state = reset(spec, 1)
    x = np.zeros((1, spec.inputs))
    outs = []
    for _ in range(4):
        out, state = step(spec, w, x, state)
        outs.append(out)
    # Same input every step, different outputs: the feedback carries the past.
    assert not np.array_equal(outs[0], outs[3])


def test_step_does_not_modify_its_arguments() -> None:
    spec = PRESETS["recurrent-small"]
    rng = np.random.default_rng(3)
    w = rng.normal(size=(2, spec.weight_count))
    x = np.ones((2, spec.inputs))
    state = rng.normal(size=(2, state_size(spec)))
    copies = (w.copy(), x.copy(), state.copy())
    for fn in (step, step_reference):
        _, new_state = fn(spec, w, x, state)
        assert not np.shares_memory(new_state, state)
        for before, after in zip(copies, (w, x, state), strict=True):
            assert np.array_equal(before, after)


def test_state_layout_most_recent_first() -> None:
    """Slot r of layer 0 holds the input of r steps ago, as the module docstring says."""
    spec = NetworkSpec(inputs=2, hidden=(3,), outputs=1, delays=2)
    plan = kernel_plan(spec)
    w = np.zeros((1, spec.weight_count))
    state = reset(spec, 1)
    for k in (1.0, 2.0, 3.0):
        _, state = step(spec, w, np.full((1, 2), k), state)
    h = int(plan.hist_off[0])
    assert state[0, h : h + 6].tolist() == [3.0, 3.0, 2.0, 2.0, 1.0, 1.0]
    # zero weights: every neuron of layers 1..M is sigmoid(0) = 0.5 in slot 0
    h1 = int(plan.hist_off[1])
    assert state[0, h1 : h1 + 3].tolist() == [0.5, 0.5, 0.5]


class Tile:
    """A tile of LANES controllers for `spec_kernel(spec)`: rows in, lanes in between.

    `lanes` maps each controller (row of the arguments) to its lane; the other lanes idle with
    zero weights, as the simulator's do.
    """

    def __init__(self, spec: NetworkSpec, weights: np.ndarray, lanes: list[int]) -> None:
        self.kernel = spec_kernel(spec)
        self.lanes = lanes
        self.w = np.zeros((spec.weight_count, LANES))
        self.w[:, lanes] = weights.T
        self.state = np.zeros((state_size(spec), LANES))
        self.x = np.zeros((spec.inputs, LANES))
        self.out = np.full((spec.outputs, LANES), np.nan)
        self.live = np.zeros(LANES, dtype=np.uint8)
        self.live[lanes] = 1
        self.spec = spec

    def step(self, state: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """Advance the rows of `state` in place (scratch full of NaN: must not matter)."""
        self.state[:, self.lanes] = state.T
        self.x[:, self.lanes] = inputs.T
        scratch = np.full((scratch_size(self.spec), LANES), np.nan)
        self.kernel(self.w, self.state, self.x, self.out, scratch, self.live)
        state[:] = self.state[:, self.lanes].T
        out: np.ndarray = self.out[:, self.lanes].T.copy()
        return out


@settings(max_examples=10, deadline=None)
@given(
    spec=specs(),
    seed=st.integers(0, 2**32 - 1),
    lanes=st.lists(st.integers(0, LANES - 1), min_size=1, max_size=LANES, unique=True),
)
def test_spec_kernel_is_step_one_bit_for_bit(
    spec: NetworkSpec, seed: int, lanes: list[int]
) -> None:
    """The generated tile kernel of any spec does in every lane exactly what the generic
    `step_one` does, whichever lanes are live."""
    rng = np.random.default_rng(seed)
    batch = len(lanes)
    w = rng.normal(scale=2.0, size=(batch, spec.weight_count))
    plan = kernel_plan(spec)
    generic = rng.normal(size=(batch, state_size(spec)))
    special = generic.copy()
    tile = Tile(spec, w, lanes)
    out_g = np.empty((batch, spec.outputs))
    scratch = np.empty(scratch_size(spec))
    for x in rng.normal(size=(8, batch, spec.inputs)):
        for r in range(batch):
            step_one(w[r], *plan, generic[r], x[r], out_g[r], scratch)
        out_s = tile.step(special, x)
        assert out_g.tobytes() == out_s.tobytes()
        assert generic.tobytes() == special.tobytes()
    idle = [lane for lane in range(LANES) if lane not in lanes]
    assert not tile.state[:, idle].any()  # zero weights and inputs keep an idle lane at 0


def test_step_one_is_the_same_call_from_python() -> None:
    spec = PRESETS["recurrent-small"]
    rng = np.random.default_rng(4)
    w = rng.normal(scale=0.3, size=(1, spec.weight_count))
    x = rng.integers(0, 2, size=(1, spec.inputs)).astype(np.float64)
    state = rng.normal(size=(1, state_size(spec)))
    out, new_state = step(spec, w, x, state)
    row = state[0].copy()
    out_row = np.empty(spec.outputs)
    step_one(w[0], *kernel_plan(spec), row, x[0], out_row, np.empty(scratch_size(spec)))
    assert np.array_equal(out_row, out[0])
    assert np.array_equal(row, new_state[0])


@pytest.mark.parametrize("activation", ["sigmoid", "linear"])
def test_motor_commands_in_range_and_compiled_twin_agrees(activation: str) -> None:
    spec = NetworkSpec(output_activation=activation)
    nan, inf = np.nan, np.inf
    y = np.array([[0.0, 1.0], [0.25, 0.5], [-3.0, 3.0], [nan, inf], [-inf, -0.0]])
    motors = motor_commands(spec, y)
    expected = {
        "sigmoid": [[-1.0, 1.0], [-0.5, 0.0], [-1.0, 1.0], [0.0, 1.0], [-1.0, -1.0]],
        "linear": [[0.0, 1.0], [0.25, 0.5], [-1.0, 1.0], [0.0, 1.0], [-1.0, -0.0]],
    }[activation]
    assert motors.tolist() == expected
    row = np.empty(2)
    for r in range(len(y)):
        motor_one(y[r], kernel_plan(spec).linear_output, row)
        assert row.tobytes() == motors[r].tobytes()


DIVERGING = NetworkSpec(hidden=(), delays=0, recurrence=1, output_activation="linear")
"""Five inputs, two linear outputs fed back to themselves (weights 18: 12 forward, 6 recurrent)."""


def diverging_weights() -> np.ndarray:
    """a(k) = [[4, .5], [.5, 4]] a(k-1) + [1, -1]: a_2 = -a_1 grows by 3.5 a step.

    Under the unbounded Eq 2 a_1 is inf after 567 steps, and the next step sums 4 inf - 0.5 inf,
    NaN: the overflow case of a fed-back linear output.
    """
    w = np.zeros((1, DIVERGING.weight_count))
    w[0, 5], w[0, 11] = 1.0, -1.0  # biases of the forward block
    w[0, 12], w[0, 13], w[0, 15], w[0, 16] = 4.0, 0.5, 0.5, 4.0  # the recurrent block
    return w


@pytest.mark.parametrize("fn", [step, step_reference])
def test_fed_back_linear_outputs_saturate_and_never_overflow(fn: StepFn) -> None:
    w = diverging_weights()
    rng = np.random.default_rng(11)
    state = reset(DIVERGING, 1)
    outs, states = [], []
    for x in rng.integers(0, 2, size=(2500, 1, DIVERGING.inputs)).astype(np.float64):
        out, state = fn(DIVERGING, w, x, state)
        outs.append(out[0])
        states.append(state[0])
    y, s = np.array(outs), np.array(states)
    assert np.isfinite(y).all() and np.isfinite(s).all()
    assert np.abs(y).max() == LINEAR_BOUND  # the bound is what stopped it
    assert y[-1].tolist() == [LINEAR_BOUND, -LINEAR_BOUND]
    first = int(np.flatnonzero(y[:, 0] == LINEAR_BOUND)[0])
    assert 5 < first < 20  # 3.5**k passes 1e6 after about 11 steps, and saturation is final
    assert (y[first:] == [LINEAR_BOUND, -LINEAR_BOUND]).all()
    assert (y[:first, 0] < LINEAR_BOUND).all()  # below the bound: plain Eq 2
    np.testing.assert_array_equal(y[1:first, 0], 3.5 * y[: first - 1, 0] + 1.0)
    motors = motor_commands(DIVERGING, y)
    assert np.isfinite(motors).all() and motors[-1].tolist() == [1.0, -1.0]


def test_non_finite_sums_of_a_linear_output_become_finite_in_every_implementation() -> None:
    """A sum that overflows saturates, one that is NaN (inf - inf) becomes 0, in all four."""
    spec = DIVERGING
    w = np.zeros(spec.weight_count)
    w[0:3] = 1e308, 1e308, -1e300  # output 1: 1e308 + 1e308 = inf, then + (-inf) = NaN
    w[6:8] = -1e308, -1e308  # output 2: -inf
    x = np.array([1.0, 1.0, 1e300, 0.0, 0.0])
    plan = kernel_plan(spec)
    results = []
    for fn in (step, step_reference):
        out, state = fn(spec, w[None], x[None], reset(spec, 1))
        results.append((out[0].tobytes(), state[0].tobytes()))
    row, out_row = reset(spec, 1)[0], np.empty(spec.outputs)
    step_one(w, *plan, row, x, out_row, np.empty(scratch_size(spec)))
    results.append((out_row.tobytes(), row.tobytes()))
    special = reset(spec, 1)
    out_s = Tile(spec, w[None], [3]).step(special, x[None])
    results.append((out_s[0].tobytes(), special[0].tobytes()))
    assert out_row.tolist() == [0.0, -LINEAR_BOUND]
    assert np.isfinite(row).all()
    assert results == [results[0]] * 4


LINEAR_FED_BACK = [
    DIVERGING,
    *(p for p in POOL if p.output_activation == "linear" and p.recurrence_of(p.layers) >= 1),
]
"""Linear-output specs with the outputs fed back (output layer depth >= 1): with the weights of
`test_large_weights_stay_finite_and_kernels_agree_bit_for_bit` they nearly always reach the
bound within 300 steps."""


@settings(max_examples=30, deadline=None)
@given(
    spec=st.sampled_from(LINEAR_FED_BACK),
    seed=st.integers(0, 2**32 - 1),
    scale=st.floats(0.5, 50.0),
)
def test_large_weights_stay_finite_and_kernels_agree_bit_for_bit(
    spec: NetworkSpec, seed: int, scale: float
) -> None:
    """Weights big enough that fed-back outputs diverge: every implementation stays finite,
    the generated kernel is `step_one` bit for bit, the numpy reference agrees with `step`,
    `motor_one` is `motor_commands` bit for bit."""
    rng = np.random.default_rng(seed)
    batch = 3
    w = rng.normal(scale=scale, size=(batch, spec.weight_count))
    xs = rng.integers(0, 2, size=(300, batch, spec.inputs)).astype(np.float64)
    plan = kernel_plan(spec)
    generic, special = reset(spec, batch), reset(spec, batch)
    tile = Tile(spec, w, [0, 5, 7])
    out_g = np.empty(spec.outputs)
    scratch = np.empty(scratch_size(spec))
    motor_g = np.empty(spec.outputs)
    for x in xs:
        out_s = tile.step(special, x)
        for r in range(batch):
            step_one(w[r], *plan, generic[r], x[r], out_g, scratch)
            assert out_g.tobytes() == out_s[r].tobytes()
            assert np.abs(out_g).max() <= LINEAR_BOUND
            motor_one(out_g, plan.linear_output, motor_g)
            assert motor_g.tobytes() == motor_commands(spec, out_g).tobytes()
        assert generic.tobytes() == special.tobytes()
    assert np.isfinite(generic).all()
    # `step` is that kernel; the reference agrees with it step by step from the same state (over
    # 300 steps the rounding differences of a chaotic controller grow, so not whole runs)
    state = reset(spec, batch)
    for x in xs:
        out_r, state_r = step_reference(spec, w, x, state)
        out, state = step(spec, w, x, state)
        assert np.isfinite(out_r).all() and np.isfinite(state_r).all()
        np.testing.assert_allclose(out_r, out, rtol=1e-12, atol=1e-3)  # sums reach ~1e10
        np.testing.assert_allclose(state_r, state, rtol=1e-12, atol=1e-3)
    assert state.tobytes() == generic.tobytes()


def test_motor_commands_rejects_wrong_width() -> None:
    with pytest.raises(ValueError, match="last dimension 2"):
        motor_commands(PRESETS["paper-best"], np.zeros((4, 3)))


@pytest.mark.parametrize("fn", [step, step_reference])
def test_shapes_are_validated(fn: StepFn) -> None:
    spec = PRESETS["paper-best"]
    w = np.zeros((2, 222))
    x = np.zeros((2, 5))
    s = reset(spec, 2)
    with pytest.raises(ValueError, match=r"weights must have shape \(batch, 222\)"):
        fn(spec, np.zeros((2, 221)), x, s)
    with pytest.raises(ValueError, match="weights must have shape"):
        fn(spec, np.zeros(222), x, s)
    with pytest.raises(ValueError, match=r"inputs must have shape \(2, 5\), got \(2, 4\)"):
        fn(spec, w, np.zeros((2, 4)), s)
    with pytest.raises(ValueError, match=r"state must have shape \(2, 48\), got \(3, 48\)"):
        fn(spec, w, x, reset(spec, 3))
    with pytest.raises(ValueError, match="batch must be >= 0"):
        reset(spec, -1)


def test_sizes_of_the_presets() -> None:
    spec = PRESETS["paper-best"]
    assert state_size(spec) == 3 * (5 + 9 + 2)
    assert scratch_size(spec) == 16
    plan = kernel_plan(spec)
    assert plan.sizes.tolist() == [5, 9, 2]
    assert plan.blocks.shape == (len(layout(spec).blocks), 5)
    assert plan is kernel_plan(spec)
    assert not plan.blocks.flags.writeable


# ---------------------------------------------------------------- disk cache of generated kernels

SMALL = NetworkSpec(inputs=2, hidden=(3,), outputs=1, delays=1, recurrence=1)
"""A spec that compiles quickly, for the fresh-process cache tests."""

PROBE = """
import numpy as np
from evorobotics.network import kernel_module, reset, step
from schemas.network import NetworkSpec
spec = NetworkSpec(inputs=2, hidden=(3,), outputs=1, delays=1, recurrence=1)
w = np.linspace(-2.0, 2.0, spec.weight_count)[None]
state = reset(spec, 1)
for k in range(6):
    out, state = step(spec, w, np.array([[k % 2, k % 3 / 2]], dtype=float), state)
print("MODULE", kernel_module(spec))
print("RESULT", out.tobytes().hex(), state.tobytes().hex())
"""


def _expected_probe() -> str:
    w = np.linspace(-2.0, 2.0, SMALL.weight_count)[None]
    state = reset(SMALL, 1)
    for k in range(6):
        out, state = step(SMALL, w, np.array([[k % 2, k % 3 / 2]], dtype=float), state)
    return f"RESULT {out.tobytes().hex()} {state.tobytes().hex()}"


def _probe(cache: Path) -> subprocess.Popen[str]:
    """A fresh interpreter running PROBE with `cache` as kernel cache, numba's cache log on."""
    env = {**os.environ, CACHE_ENV: str(cache), "NUMBA_DEBUG_CACHE": "1"}
    return subprocess.Popen(
        [sys.executable, "-W", "error", "-c", PROBE],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _finish(proc: subprocess.Popen[str]) -> tuple[str, str, list[str]]:
    """(module name, RESULT line, numba cache log lines about that module) of a PROBE run."""
    stdout, stderr = proc.communicate(timeout=100)
    assert proc.returncode == 0, stderr
    lines = stdout.splitlines()
    module = next(line.split()[1] for line in lines if line.startswith("MODULE"))
    result = next(line for line in lines if line.startswith("RESULT"))
    return module, result, [line for line in lines if line.startswith("[cache]") and module in line]


def test_warm_cache_gives_the_same_bits_and_corrupt_files_are_regenerated(tmp_path: Path) -> None:
    expected = _expected_probe()
    module, cold, log = _finish(_probe(tmp_path))
    assert cold == expected
    assert any("data saved" in line for line in log)
    source = tmp_path / f"{module}.py"
    pristine = source.read_bytes()

    _, warm, log = _finish(_probe(tmp_path))
    assert warm == expected
    assert any("data loaded" in line for line in log)
    assert not any("saved" in line for line in log)

    # a half-written module and truncated machine code: detected, rebuilt, same bits
    source.write_bytes(pristine[: len(pristine) // 2])
    for data in (tmp_path / "__pycache__").glob(f"{module}.*.nbc"):
        data.write_bytes(data.read_bytes()[:100])
    _, repaired, log = _finish(_probe(tmp_path))
    assert repaired == expected
    assert source.read_bytes() == pristine
    assert any("data saved" in line for line in log)
    _, again, log = _finish(_probe(tmp_path))
    assert again == expected
    assert not any("saved" in line for line in log)


def test_concurrent_first_use_is_safe(tmp_path: Path) -> None:
    expected = _expected_probe()
    first, second = _probe(tmp_path), _probe(tmp_path)
    results = [_finish(first), _finish(second)]
    assert [r[1] for r in results] == [expected, expected]
    module = results[0][0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["__pycache__", f"{module}.py"]
    _, warm, log = _finish(_probe(tmp_path))
    assert warm == expected
    assert not any("saved" in line for line in log)


def test_cached_module_names_by_content_and_rewrites_damaged_files(tmp_path: Path) -> None:
    dep = tmp_path / "dep.py"
    dep.write_text("A = 1\n")
    one = cached_module("probe", "VALUE = 1\n", (str(dep),), tmp_path / "c")
    assert one.VALUE == 1
    assert cached_module("probe", "VALUE = 1\n", (str(dep),), tmp_path / "c") is one
    other = cached_module("probe", "VALUE = 2\n", (str(dep),), tmp_path / "c")
    assert other.__name__ != one.__name__ and other.VALUE == 2
    # a dependency with other bytes (an edited evorobotics/network.py): a new module too
    edited = tmp_path / "edited.py"
    edited.write_text("A = 2\n")
    third = cached_module("probe", "VALUE = 1\n", (str(edited),), tmp_path / "c")
    assert third.__name__ not in (one.__name__, other.__name__) and third.VALUE == 1
    path = tmp_path / "c" / f"{one.__name__}.py"
    pristine = path.read_bytes()
    path.write_bytes(pristine[:-3])  # a torn write
    del sys.modules[one.__name__]
    assert cached_module("probe", "VALUE = 1\n", (str(dep),), tmp_path / "c").VALUE == 1
    assert path.read_bytes() == pristine
    with pytest.raises(ValueError, match="identifier"):
        cached_module("not a name", "VALUE = 1\n", (), tmp_path / "c")


def test_kernel_cache_dir_honours_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "k"))
    assert kernel_cache_dir() == tmp_path / "k"
    monkeypatch.delenv(CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert kernel_cache_dir() == tmp_path / "xdg" / "evocolony" / "kernels"
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)  # writable by others: never imported from
    monkeypatch.setenv(CACHE_ENV, str(shared))
    fallback = kernel_cache_dir()
    assert fallback != shared and fallback.is_dir() and os.access(fallback, os.W_OK)


def test_threads_importing_one_generated_module_at_once_all_see_it_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The first import stops halfway (its body waits on `release`); the other threads ask for
    # the module meanwhile and must wait for it whole, never get it half executed.
    hooks = types.ModuleType("race_hooks")
    hooks.started, hooks.release = threading.Event(), threading.Event()  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "race_hooks", hooks)
    source = (
        "import race_hooks\nrace_hooks.started.set()\nrace_hooks.release.wait(30)\ndone = True\n"
    )
    seen: list[bool] = []
    errors: list[BaseException] = []
    returned = threading.Semaphore(0)

    def load() -> None:
        try:
            seen.append(cached_module("race", source, directory=tmp_path).done)
        except BaseException as exc:
            errors.append(exc)
        returned.release()

    first = threading.Thread(target=load)
    first.start()
    assert hooks.started.wait(30)
    others = [threading.Thread(target=load) for _ in range(4)]
    for t in others:
        t.start()
    early = returned.acquire(timeout=0.5)  # nobody may come back before the module is whole
    hooks.release.set()
    for t in [first, *others]:
        t.join(timeout=30)
    assert not early and errors == [] and seen == [True] * 5


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.floats(-50.0, 50.0),
            st.floats(allow_nan=True, allow_infinity=True),
            st.sampled_from([0.0, -0.0, 708.0, -708.0, 709.0, -745.0, 36.7]),
        ),
        min_size=LANES,
        max_size=LANES,
    ),
    st.lists(st.booleans(), min_size=LANES, max_size=LANES),
)
def test_sigmoid_rows_are_sigmoid_bit_for_bit_and_within_an_ulp_of_exp(
    values: list[float], live: list[bool]
) -> None:
    """The SIMD sigmoid is the scalar one in every live lane of each of the rows it interleaves
    (idle lanes keep their value), and its exp is within an ulp of numpy's down to -708, below
    which it is 0."""
    rows = np.array([values, values[::-1], [-v for v in values]])
    given = rows.copy()
    _sigmoid_lanes(rows, np.array(live, dtype=np.uint8))
    for (r, k), u in np.ndenumerate(given):
        expected = _sigmoid(u) if live[k] else u
        assert np.array([rows[r, k]]).tobytes() == np.array([expected]).tobytes()
    for u in values:
        x = -abs(u)
        if np.isfinite(x) and x > -708.0:
            assert abs(_exp_neg(x) - math.exp(x)) <= np.spacing(math.exp(x))
        elif not math.isnan(x):
            assert _exp_neg(x) == 0.0


@njit
def _sigmoid_lanes(rows: np.ndarray, live: np.ndarray) -> None:
    _sigmoid_rows(rows, 0, 3, live)  # type: ignore[call-arg, arg-type]  # numba supplies typingctx
