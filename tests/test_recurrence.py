"""Per-layer recurrence depths: layout, weight count, validation, JSON, and a controller running.

A spec's `recurrence` is one depth S for every layer or a tuple of one depth per layer; the
network kernels and the GA see only the layout, so the layout is where the two forms must meet.
"""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from colony.cli import app
from evorobotics import network
from evorobotics.document import ControllerDocument
from evorobotics.evaluate import start_poses
from evorobotics.layout import Layout, layout
from evorobotics.maze import load_maze
from evorobotics.sim import simulate, simulate_reference
from schemas.network import PRESETS, NetworkSpec
from schemas.run import RunConfig

HIDDEN_ONLY = NetworkSpec(hidden=(9,), delays=2, recurrence=(1, 0))
"""paper-best plus the hidden layer's self-feedback, and no output feedback."""


def _blocks(lay: Layout) -> list[tuple[int, ...]]:
    return [(b.m, b.t, b.s, b.src, b.rows, b.cols, b.offset) for b in lay.blocks]


@st.composite
def shapes(draw: st.DrawFn) -> tuple[tuple[int, ...], int, int]:
    """(hidden sizes, delays T, inputs) of a small network."""
    hidden = tuple(draw(st.lists(st.integers(1, 6), max_size=3)))
    return hidden, draw(st.integers(0, 3)), draw(st.integers(1, 5))


@st.composite
def per_layer_specs(draw: st.DrawFn) -> NetworkSpec:
    """Small specs with a valid depth for each layer m: 0..M-m+1."""
    hidden, delays, inputs = draw(shapes())
    layers = len(hidden) + 1
    depths = tuple(draw(st.integers(0, layers - m + 1)) for m in range(1, layers + 1))
    return NetworkSpec(inputs=inputs, hidden=hidden, delays=delays, recurrence=depths)


@given(shape=shapes(), data=st.data())
def test_an_int_depth_is_the_tuple_of_its_depths_per_layer(
    shape: tuple[tuple[int, ...], int, int], data: st.DataObject
) -> None:
    hidden, delays, inputs = shape
    layers = len(hidden) + 1
    depth = data.draw(st.integers(0, layers))
    as_int = NetworkSpec(inputs=inputs, hidden=hidden, delays=delays, recurrence=depth)
    per_layer = tuple(min(depth, layers - m + 1) for m in range(1, layers + 1))
    as_tuple = as_int.model_copy(update={"recurrence": per_layer})
    assert NetworkSpec.model_validate(as_tuple.model_dump()) == as_tuple
    assert [as_int.recurrence_of(m) for m in range(1, layers + 1)] == list(per_layer)
    assert _blocks(layout(as_int)) == _blocks(layout(as_tuple))
    assert as_int.weight_count == as_tuple.weight_count == layout(as_tuple).n_weights
    if depth <= 1:  # the same depth for every layer is valid only up to the output layer's 1
        equal = NetworkSpec(
            inputs=inputs, hidden=hidden, delays=delays, recurrence=(depth,) * layers
        )
        assert _blocks(layout(equal)) == _blocks(layout(as_int))
        assert equal.weight_count == as_int.weight_count


@given(spec=per_layer_specs())
def test_weight_count_is_the_sum_of_the_blocks_and_each_layer_has_its_levels(
    spec: NetworkSpec,
) -> None:
    lay = layout(spec)
    assert spec.weight_count == sum(b.size for b in lay.blocks) == lay.n_weights
    offsets = [b.offset for b in lay.blocks]
    assert offsets == sorted(offsets) and offsets[0] == 0
    assert [(b.m, b.t, b.s) for b in lay.blocks] == sorted((b.m, b.t, b.s) for b in lay.blocks)
    assert isinstance(spec.recurrence, tuple)
    for m, depth in enumerate(spec.recurrence, start=1):
        for t in range(spec.delays + 1):
            levels = [b.s for b in lay.blocks if b.m == m and b.t == t]
            assert levels == list(range(depth + 1))
        assert spec.source(m, depth) == m - 1 + depth
        assert spec.source(m, depth + 1) is None
    w = np.arange(lay.n_weights, dtype=np.float64)
    assert np.array_equal(np.concatenate([lay.view(w, b).ravel() for b in lay.blocks]), w)


def test_hidden_only_feedback_has_no_output_self_feedback() -> None:
    lay = layout(HIDDEN_ONLY)
    assert {(b.m, b.s) for b in lay.blocks} == {(1, 0), (1, 1), (2, 0)}
    assert not [b for b in lay.blocks if b.m == 2 and b.s >= 1]
    assert HIDDEN_ONLY.source(2, 1) is None and HIDDEN_ONLY.source(1, 1) == 1
    # per lag: 9 x (5 + 1) from the inputs, 9 x (9 + 1) from itself, 2 x (9 + 1) outputs
    assert HIDDEN_ONLY.weight_count == 3 * (54 + 90 + 20) == 492
    fig1b = PRESETS["fig1b"]
    assert [b for b in layout(fig1b).blocks if b.m == fig1b.layers and b.s >= 1] == []
    assert {b.src for b in layout(fig1b).blocks if b.s >= 1} == {1, 2}


@settings(max_examples=25, deadline=None)
@given(spec=per_layer_specs(), seed=st.integers(0, 2**32 - 1))
def test_per_layer_depths_are_the_deepest_int_network_with_the_other_levels_zero(
    spec: NetworkSpec, seed: int
) -> None:
    """Each block keeps its meaning: copied into the network whose int S is the deepest depth,
    with every block the tuple lacks zero, it gives the same outputs step by step."""
    assert isinstance(spec.recurrence, tuple)
    wide = spec.model_copy(update={"recurrence": max(spec.recurrence)})
    rng = np.random.default_rng(seed)
    w = rng.normal(scale=1.5, size=(3, spec.weight_count))
    w_wide = np.zeros((3, wide.weight_count))
    wide_blocks = {(b.m, b.t, b.s): b for b in layout(wide).blocks}
    for b in layout(spec).blocks:
        layout(wide).view(w_wide, wide_blocks[b.m, b.t, b.s])[...] = layout(spec).view(w, b)
    state, state_wide = network.reset(spec, 3), network.reset(wide, 3)
    for x in rng.integers(0, 2, size=(8, 3, spec.inputs)).astype(np.float64):
        out, state = network.step_reference(spec, w, x, state)
        out_wide, state_wide = network.step_reference(wide, w_wide, x, state_wide)
        assert np.array_equal(out, out_wide)


@pytest.mark.parametrize("spec", [HIDDEN_ONLY, PRESETS["fig1b"]], ids=["(1, 0)", "fig1b"])
def test_hidden_feedback_controller_simulates_like_the_reference_and_the_robot_step(
    spec: NetworkSpec,
) -> None:
    maze = load_maze("paper")
    weights = np.random.default_rng(3).normal(0.0, 1.5, (8, spec.weight_count))
    starts = np.tile(start_poses(maze, 4, 0, 4), (2, 1))
    fast = simulate(spec, weights, maze, starts, 40, record=True)
    ref = simulate_reference(spec, weights, maze, starts, 40, record=True)
    assert fast.poses is not None and ref.poses is not None
    assert fast.whiskers is not None and ref.whiskers is not None
    assert fast.motors is not None and ref.motors is not None
    assert np.allclose(fast.poses, ref.poses, atol=1e-9)
    assert np.array_equal(fast.whiskers, ref.whiskers)
    assert np.allclose(fast.motors, ref.motors, atol=1e-9)
    assert np.allclose(fast.components, ref.components, atol=1e-9)
    assert fast.whiskers.any()
    # the robot runs network.step once per step on what its whiskers read
    state = network.reset(spec, 8)
    for k in range(40):
        out, state = network.step(spec, weights, fast.whiskers[:, k].astype(np.float64), state)
        assert network.motor_commands(spec, out).tobytes() == fast.motors[:, k].tobytes()


def test_run_config_takes_a_spec_with_per_layer_depths_as_rest_json() -> None:
    body = json.dumps(
        {"network": {"hidden": [9], "delays": 2, "recurrence": [1, 0]}, "generations": 3}
    )
    config = RunConfig.model_validate_json(body)
    assert config.network_spec == HIDDEN_ONLY
    assert config.network_spec.recurrence == (1, 0)
    assert RunConfig.model_validate_json(config.model_dump_json()) == config
    int_spec = RunConfig.model_validate_json('{"network": {"recurrence": 1}}').network_spec
    assert int_spec.recurrence == 1 and int_spec.weight_count == 3 * (54 + 90 + 20 + 2 * 3)


@given(spec=per_layer_specs())
def test_per_layer_specs_and_their_controllers_round_trip_through_json(spec: NetworkSpec) -> None:
    assert NetworkSpec.model_validate_json(spec.model_dump_json()) == spec
    doc = ControllerDocument(spec, np.linspace(-1.0, 1.0, spec.weight_count))
    back = ControllerDocument.from_json(doc.to_json())
    assert back == doc and back.spec.recurrence == spec.recurrence


def test_an_int_spec_keeps_its_json_and_controller_id() -> None:
    """Int depths serialise as before, so stored controllers keep their sha256."""
    spec = PRESETS["recurrent-small"]
    assert json.loads(spec.model_dump_json())["recurrence"] == 2
    doc = ControllerDocument(spec, np.zeros(spec.weight_count))
    as_tuple = spec.model_copy(update={"recurrence": (2, 1)})
    assert ControllerDocument(as_tuple, np.zeros(spec.weight_count)).sha256 != doc.sha256


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"hidden": [9], "recurrence": [1]}, r"recurrence has 1 depth\(s\) but .* 2 layer\(s\)"),
        ({"hidden": [9], "recurrence": [1, 0, 0]}, r"recurrence has 3 depth\(s\)"),
        ({"hidden": [9], "recurrence": [1, 2]}, r"depth 2 of layer 2 is outside 0\.\.1"),
        ({"hidden": [4, 4], "recurrence": [4, 0, 0]}, r"depth 4 of layer 1 is outside 0\.\.3"),
        ({"hidden": [9], "recurrence": [-1, 0]}, r"depth -1 of layer 1 is outside 0\.\.2"),
        ({"hidden": [9], "recurrence": -1}, r"recurrence depth -1 is outside 0\.\.2"),
        ({"hidden": [], "recurrence": 2}, r"recurrence depth 2 is outside 0\.\.1"),
        ({"hidden": [9], "recurrence": ["a", 0]}, r"recurrence"),
    ],
)
def test_bad_recurrence_is_rejected_naming_the_problem(
    fields: dict[str, object], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        NetworkSpec.model_validate_json(json.dumps(fields))
    with pytest.raises(ValueError, match=message):
        RunConfig.model_validate_json(json.dumps({"network": fields}))


def test_recurrence_of_a_layer_that_does_not_exist_is_an_error() -> None:
    with pytest.raises(ValueError, match=r"layer 3 is outside 1\.\.2"):
        HIDDEN_ONLY.recurrence_of(3)
    with pytest.raises(ValueError, match=r"layer 0 is outside 1\.\.2"):
        HIDDEN_ONLY.source(0, 0)


def test_colony_presets_prints_per_layer_depths_as_a_list() -> None:
    result = CliRunner().invoke(app, ["presets"])
    assert result.exit_code == 0, result.output
    lines = {line.split()[0]: line for line in result.output.splitlines()}
    assert "396 weights  hidden=[5, 5] T=2 S=[1, 1, 0] out=sigmoid" in lines["fig1b"]
    assert "T=1 S=2 out=sigmoid" in lines["recurrent-small"]
