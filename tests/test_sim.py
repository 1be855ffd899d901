"""The simulator: whisker geometry, kinematics, blocked moves, stuck rule, kernel vs reference."""

import hashlib
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from numba import njit

from evorobotics import network
from evorobotics.evaluate import draw_gap, start_poses
from evorobotics.maze import load_maze
from evorobotics.sim import (
    DEFAULT_WORLD,
    SINCOS_LIMIT,
    Gap,
    _episode_kernel,
    _sincos,
    _sincos_tile,
    body_hits_wall,
    clear_of_walls,
    simulate,
    simulate_reference,
    whisker_bits,
)
from schemas.network import PRESETS, NetworkSpec
from schemas.world import World

ARENA = load_maze("arena")  # 2 m room, inner faces at 0.1 and 1.9
CONST = NetworkSpec(hidden=(), delays=0, output_activation="linear")
"""Linear outputs, no hidden layer: with only the biases set, wheel commands are constants."""
FLIP = NetworkSpec(hidden=(), delays=0, recurrence=1, output_activation="linear")
"""out(k) = 1 - 2 out(k-1): full forward, full reverse, forward, ... (sign alternates)."""


def const_weights(left: float, right: float, batch: int = 1) -> np.ndarray:
    w = np.zeros((batch, CONST.weight_count))
    w[:, 5], w[:, 11] = left, right
    return w


def flip_weights() -> np.ndarray:
    w = np.zeros((1, FLIP.weight_count))
    w[0, 5] = w[0, 11] = 1.0
    w[0, 12] = w[0, 16] = -2.0
    return w


def sense(pose: tuple[float, float, float], rng: float | None = None) -> tuple[list[int], ...]:
    """Whisker bits by the reference and by the kernel (first recorded step)."""
    poses = np.array([pose])
    ranges = None if rng is None else np.array([rng])
    ref = whisker_bits(ARENA, poses, ranges=ranges)[0].tolist()
    gap = None if rng is None else Gap(np.array([rng]), np.ones((1, 2)))
    res = simulate(CONST, const_weights(0, 0), ARENA, poses, 1, gap=gap, record=True)
    assert res.whiskers is not None
    return ref, res.whiskers[0, 0].tolist()


@pytest.mark.parametrize("q", range(5))
@pytest.mark.parametrize(("dist", "bit"), [(0.049, 1), (0.051, 0)])
def test_each_whisker_triggers_at_exactly_50mm(q: int, dist: float, bit: int) -> None:
    # turn the robot so whisker q points due east at the east face (x = 1.9)
    p = DEFAULT_WORLD
    th = -p.whisker_angle[q]
    ax = p.whisker_x[q] * math.cos(th) - p.whisker_y[q] * math.sin(th)
    ay = p.whisker_x[q] * math.sin(th) + p.whisker_y[q] * math.cos(th)
    pose = (1.9 - dist - ax, 1.0 - ay, th)
    ref, kern = sense(pose)
    assert ref[q] == kern[q] == bit
    assert ref == kern


def test_straight_ahead_only_the_middle_whisker() -> None:
    x = 1.9 - 0.0825 - 0.049
    assert sense((x, 1.0, 0.0)) == ([0, 0, 1, 0, 0],) * 2
    assert sense((x - 0.002, 1.0, 0.0)) == ([0, 0, 0, 0, 0],) * 2
    # whisker order is left to right: facing east near the north wall only the left ones see it
    assert sense((1.0, 1.9 - 0.095, 0.0))[0][:2] == [1, 0]
    assert sense((1.0, 1.9 - 0.095, 0.0))[0][3:] == [0, 0]


def test_reality_gap_whisker_range() -> None:
    x = 1.9 - 0.0825
    assert sense((x - 0.099, 1.0, 0.0), rng=0.1) == ([0, 0, 1, 0, 0],) * 2
    assert sense((x - 0.101, 1.0, 0.0), rng=0.1) == ([0, 0, 0, 0, 0],) * 2
    assert sense((x - 0.024, 1.0, 0.0), rng=0.025) == ([0, 0, 1, 0, 0],) * 2
    assert sense((x - 0.026, 1.0, 0.0), rng=0.025)[0][2] == 0


def test_straight_line_and_spin_kinematics() -> None:
    p = DEFAULT_WORLD
    start = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    w = np.concatenate([const_weights(1, 1), const_weights(-1, 1)])
    res = simulate(CONST, w, ARENA, start, 10, record=True)
    step = p.max_speed * p.dt
    assert res.poses_final[0] == pytest.approx([1.0 + 10 * step, 1.0, 0.0])
    assert res.curve_length[0] == pytest.approx(10 * step)
    assert res.net_offset[0] == pytest.approx(10 * step)
    assert res.max_offset[0] == pytest.approx(10 * step)
    spin = 2 * p.max_speed / p.wheel_base * p.dt
    assert res.poses_final[1, :2] == pytest.approx([1.0, 1.0])
    wrapped = (10 * spin + math.pi) % (2 * math.pi) - math.pi
    assert res.poses_final[1, 2] == pytest.approx(wrapped)
    assert res.curve_length[1] == pytest.approx(0.0, abs=1e-12)
    assert not res.stuck.any()


def test_motor_gain_scales_each_wheel() -> None:
    start = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    gap = Gap(np.full(2, 0.05), np.array([[1.1, 1.1], [0.9, 1.1]]))
    res = simulate(CONST, const_weights(1, 1, 2), ARENA, start, 5, gap=gap)
    assert res.curve_length[0] == pytest.approx(5 * 1.1 * 0.03)
    assert res.poses_final[1, 2] > 0.0  # faster right wheel turns left


def test_driving_into_a_wall_blocks_then_sticks() -> None:
    # facing east, front edge 0.5 m from the east face: 16 free steps of 30 mm, then blocked
    start = np.array([[1.9 - 0.0825 - 0.5, 1.0, 0.0]])
    res = simulate(CONST, const_weights(1, 1), ARENA, start, 40, record=True)
    assert res.poses is not None
    assert bool(res.stuck[0])
    assert res.curve_length[0] == pytest.approx(16 * 0.03)
    assert (res.poses[0, 17:] == res.poses[0, 16]).all()
    patient = World(stuck_after=100)
    res2 = simulate(CONST, const_weights(1, 1), ARENA, start, 40, params=patient)
    assert not res2.stuck[0]
    assert res2.poses_final[0] == pytest.approx(res.poses_final[0])


@pytest.mark.parametrize("gap_kind", ["nominal", "trial", "step"])
def test_robots_pushing_into_a_wall_sense_what_the_numpy_geometry_senses(gap_kind: str) -> None:
    # blocked step after step on the same candidate pose, never stuck: every recorded bit is
    # the exact test's at that pose and that step's ranges (per-step draws change them while
    # the pose stands still)
    steps, batch = 30, 6
    east = 1.9 - DEFAULT_WORLD.body_length / 2
    start = np.array([[east - 0.1, 0.4 + 0.2 * n, 0.3 * (n - 2.5)] for n in range(batch)])
    g = np.random.default_rng(5)
    gap = {
        "nominal": None,
        "trial": Gap(g.uniform(0.0, 0.12, batch), np.ones((batch, 2))),
        "step": Gap(g.uniform(0.0, 0.12, (batch, steps, 5)), np.ones((batch, 2))),
    }[gap_kind]
    params = World(stuck_after=10**6)
    w = const_weights(1.0, 0.9, batch)
    res = simulate(CONST, w, ARENA, start, steps, params, gap, record=True)
    assert res.poses is not None and res.whiskers is not None
    assert (res.poses[:, -1] == res.poses[:, -10]).all()  # blocked for the last steps
    for k in range(steps + 1):
        assert not body_hits_wall(ARENA, res.poses[:, k]).any()
    for k in range(steps):
        ranges = None if gap is None else gap.whisker_range
        if ranges is not None and ranges.ndim == 3:
            ranges = ranges[:, k]
        assert (res.whiskers[:, k] == whisker_bits(ARENA, res.poses[:, k], params, ranges)).all()
    ref = simulate_reference(CONST, w, ARENA, start, steps, params, gap)
    assert ref.poses_final == pytest.approx(res.poses_final, abs=1e-9)


def test_stuck_robot_stays_immobile_but_blocked_one_can_back_off() -> None:
    # front 15 mm from the wall; the controller alternates full forward / full reverse
    start = np.array([[1.9 - 0.0825 - 0.015, 1.0, 0.0]])
    res = simulate(FLIP, flip_weights(), ARENA, start, 20, record=True)
    assert res.poses is not None and res.motors is not None
    assert res.motors[0, 1, 0] == -1.0  # reverse was commanded after the block ...
    assert bool(res.stuck[0]) and res.curve_length[0] == 0.0  # ... but stuck never moves
    assert (res.poses[0] == res.poses[0, 0]).all()
    res2 = simulate(FLIP, flip_weights(), ARENA, start, 20, params=World(stuck_after=2))
    assert not res2.stuck[0]
    assert res2.curve_length[0] == pytest.approx(0.03 * 19)


@settings(max_examples=40, deadline=None)
@given(
    x=st.floats(0.1, 2.3),
    y=st.floats(0.1, 2.3),
    th=st.floats(-math.pi, math.pi),
    left=st.floats(-1, 1),
    right=st.floats(-1, 1),
    stuck_after=st.integers(1, 5),
)
def test_blocked_moves_never_enter_walls(
    x: float, y: float, th: float, left: float, right: float, stuck_after: int
) -> None:
    maze = load_maze("paper")
    start = np.array([[x, y, th]])
    assume(not body_hits_wall(maze, start)[0])
    params = World(stuck_after=stuck_after)
    res = simulate(CONST, const_weights(left, right), maze, start, 30, params, record=True)
    assert res.poses is not None
    assert not body_hits_wall(maze, res.poses[0]).any()
    ref = simulate_reference(CONST, const_weights(left, right), maze, start, 30, params)
    assert ref.poses_final == pytest.approx(res.poses_final, abs=1e-9)
    assert ref.stuck[0] == res.stuck[0]


def test_body_collision_is_the_rectangle() -> None:
    # east face at x = 1.9: the front edge may touch it, not cross it
    p = DEFAULT_WORLD
    near = np.array([[1.9 - p.body_length / 2 - 1e-9, 1.0, 0.0]])
    over = np.array([[1.9 - p.body_length / 2 + 1e-6, 1.0, 0.0]])
    side = np.array([[1.9 - p.body_width / 2 - 1e-9, 1.0, math.pi / 2]])
    assert not body_hits_wall(ARENA, near)[0]
    assert body_hits_wall(ARENA, over)[0]
    assert not body_hits_wall(ARENA, side)[0]
    assert body_hits_wall(ARENA, np.array([[-1.0, 1.0, 0.0]]))[0]  # outside is wall


@pytest.mark.parametrize(
    ("preset", "batch", "steps"),
    [("paper-best", 96, 40), ("recurrent-small", 48, 40), ("paper-largest", 8, 15)],
)
@pytest.mark.parametrize("with_gap", ["none", "shared", "per-whisker", "nominal-world"])
def test_kernel_agrees_with_reference(preset: str, batch: int, steps: int, with_gap: str) -> None:
    # whisker ranges shared by the five or one per whisker, in a gap or as a world's nominal
    spec = PRESETS[preset]
    maze = load_maze("paper")
    g = np.random.default_rng(7)
    weights = g.normal(0.0, 1.0, (batch, spec.weight_count))
    starts = np.tile(start_poses(maze, 3, 0, 8), (batch // 8, 1))
    gap, world = None, World()
    if with_gap == "shared":
        gap = Gap(g.uniform(0.025, 0.1, batch), g.uniform(0.85, 1.15, (batch, 2)))
    elif with_gap == "per-whisker":
        gap = Gap(g.uniform(0.025, 0.1, (batch, 5)), g.uniform(0.85, 1.15, (batch, 2)))
    elif with_gap == "nominal-world":
        world = World(whisker_range=(0.03, 0.09, 0.025, 0.06, 0.1), motor_gain=(0.88, 1.13))
    fast = simulate(spec, weights, maze, starts, steps, world, gap, record=True)
    ref = simulate_reference(spec, weights, maze, starts, steps, world, gap, record=True)
    assert fast.poses is not None and ref.poses is not None
    assert fast.whiskers is not None and ref.whiskers is not None
    assert fast.motors is not None and ref.motors is not None
    assert np.allclose(fast.poses, ref.poses, atol=1e-9)
    assert np.array_equal(fast.whiskers, ref.whiskers)
    assert np.allclose(fast.motors, ref.motors, atol=1e-9)
    assert np.array_equal(fast.stuck, ref.stuck)
    assert np.allclose(fast.components, ref.components, atol=1e-9)
    assert fast.cells is not None and ref.cells is not None
    assert np.array_equal(fast.cells, ref.cells)
    assert (fast.cells >= 1).all() and (fast.cells > 1).any()
    assert fast.whiskers.any()  # the test does exercise sensing


def test_kernel_results_do_not_depend_on_batch() -> None:
    spec = PRESETS["paper-best"]
    maze = load_maze("paper")
    weights = np.random.default_rng(1).normal(size=(20, spec.weight_count))
    starts = np.tile(start_poses(maze, 0, 0, 4), (5, 1))
    whole = simulate(spec, weights, maze, starts, 40)
    parts = [simulate(spec, weights[a:b], maze, starts[a:b], 40) for a, b in ((0, 3), (3, 20))]
    assert whole.components.tobytes() == np.concatenate([p.components for p in parts]).tobytes()
    cells = [p.cells for p in parts if p.cells is not None]
    assert whole.cells is not None and whole.cells.tobytes() == np.concatenate(cells).tobytes()
    assert whole.poses_final.tobytes() == np.concatenate([p.poses_final for p in parts]).tobytes()


@pytest.mark.parametrize("preset", ["paper-best", "recurrent-small"])
def test_replaying_recorded_whiskers_through_network_step_gives_the_same_motors(
    preset: str,
) -> None:
    # the robot runs network.step once per step; the simulation ran the fused kernel
    spec = PRESETS[preset]
    maze = load_maze("paper")
    g = np.random.default_rng(5)
    weights = g.normal(0.0, 1.5, (12, spec.weight_count))
    starts = np.tile(start_poses(maze, 2, 0, 4), (3, 1))
    gap = Gap(g.uniform(0.025, 0.1, 12), g.uniform(0.85, 1.15, (12, 2)))
    res = simulate(spec, weights, maze, starts, 40, gap=gap, record=True)
    assert res.whiskers is not None and res.motors is not None
    assert res.whiskers.any() and res.stuck.any()
    for rows in (slice(0, 12), slice(4, 5)):  # the whole batch, and one robot alone
        state = network.reset(spec, weights[rows].shape[0])
        for k in range(40):
            bits = res.whiskers[rows, k].astype(np.float64)
            out, state = network.step(spec, weights[rows], bits, state)
            motors = network.motor_commands(spec, out)
            assert motors.tobytes() == res.motors[rows, k].tobytes()


def test_bad_arguments() -> None:
    spec = PRESETS["paper-best"]
    w = np.zeros((2, spec.weight_count))
    with pytest.raises(ValueError, match="start_poses"):
        simulate(spec, w, ARENA, np.zeros((3, 3)), 5)
    with pytest.raises(ValueError, match="weights"):
        simulate(spec, w[:, 1:], ARENA, np.zeros((2, 3)), 5)
    with pytest.raises(ValueError, match="inputs"):
        simulate(NetworkSpec(inputs=4), np.zeros((2, 50)), ARENA, np.zeros((2, 3)), 5)
    with pytest.raises(ValueError, match="gap"):
        simulate(spec, w, ARENA, np.ones((2, 3)), 5, gap=Gap(np.ones(3), np.ones((2, 2))))
    with pytest.raises(ValueError, match="stuck_after"):
        World(stuck_after=0)


def test_recording_does_not_change_results() -> None:
    # without recording the kernel stops a stuck robot early; the terms must be the same
    spec = PRESETS["paper-best"]
    maze = load_maze("paper")
    weights = np.random.default_rng(2).normal(size=(64, spec.weight_count))
    starts = np.tile(start_poses(maze, 1, 0, 8), (8, 1))
    quiet = simulate(spec, weights, maze, starts, 40)
    loud = simulate(spec, weights, maze, starts, 40, record=True)
    assert quiet.stuck.any()
    assert quiet.components.tobytes() == loud.components.tobytes()
    assert quiet.poses_final.tobytes() == loud.poses_final.tobytes()


@settings(max_examples=200, deadline=None)
@given(
    x=st.floats(-0.1, 2.5),
    y=st.floats(-0.1, 2.5),
    th=st.floats(-math.pi, math.pi),
    rng=st.floats(0.0, 0.1),
)
def test_kernel_whiskers_match_reference_anywhere(
    x: float, y: float, th: float, rng: float
) -> None:
    # the kernel's clearance-map early outs must never change a bit
    maze = load_maze("paper")
    poses = np.array([[x, y, th]])
    ref = whisker_bits(maze, poses, ranges=np.array([rng]))
    gap = Gap(np.array([rng]), np.ones((1, 2)))
    res = simulate(CONST, const_weights(0, 0), maze, poses, 1, gap=gap, record=True)
    assert res.whiskers is not None
    assert np.array_equal(res.whiskers[:, 0], ref)


SIM_PROBE = """
import numpy as np
from evorobotics.evaluate import start_poses
from evorobotics.maze import load_maze
from evorobotics.sim import simulate
from schemas.network import NetworkSpec
spec = NetworkSpec(hidden=(), delays=1, output_activation="linear")
maze = load_maze("arena")
w = np.random.default_rng(7).normal(0.0, 1.5, (6, spec.weight_count))
res = simulate(spec, w, maze, start_poses(maze, 0, 0, 6), 30, record=True)
print("RESULT", res.poses.tobytes().hex(), res.components.tobytes().hex())
"""


def test_fresh_process_with_warm_kernel_cache_gives_the_same_bits(tmp_path: Path) -> None:
    spec = NetworkSpec(hidden=(), delays=1, output_activation="linear")
    w = np.random.default_rng(7).normal(0.0, 1.5, (6, spec.weight_count))
    res = simulate(spec, w, ARENA, start_poses(ARENA, 0, 0, 6), 30, record=True)
    assert res.poses is not None
    expected = f"RESULT {res.poses.tobytes().hex()} {res.components.tobytes().hex()}"
    env = {**os.environ, network.CACHE_ENV: str(tmp_path), "NUMBA_DEBUG_CACHE": "1"}
    logs = []
    for _ in range(2):  # cold, then warm
        done = subprocess.run(
            [sys.executable, "-W", "error", "-c", SIM_PROBE],
            env=env,
            capture_output=True,
            text=True,
            timeout=100,
            check=True,
        )
        lines = done.stdout.splitlines()
        assert [line for line in lines if line.startswith("RESULT")] == [expected]
        logs.append([line for line in lines if "evocolony_episodes_" in line])
    assert any("data saved" in line for line in logs[0])
    assert any("data loaded" in line for line in logs[1])
    assert not any("saved" in line for line in logs[1])


CHECK_MAZES = ["arena", "corridor", "paper", "zigzag", "gen:4:2"]
CHECK_WORLDS = [
    DEFAULT_WORLD,
    World(whisker_range=0.1),
    World(body_length=0.3, body_width=0.2),
    World(whisker_range=0.0),
]


@settings(max_examples=40, deadline=None)
@given(
    name=st.sampled_from(CHECK_MAZES),
    params=st.sampled_from(CHECK_WORLDS),
    seed=st.integers(0, 2**32 - 1),
)
def test_clear_of_walls_is_the_numpy_test_bit_for_bit(name: str, params: World, seed: int) -> None:
    # the start-pose check: random poses, plus a quarter-cell lattice at headings k pi / 4
    # (poses exactly on cell edges and axis-parallel whiskers, where rounding would show)
    maze = load_maze(name)
    g = np.random.default_rng(seed)
    uniform = np.column_stack(
        [
            g.uniform(0.0, maze.width, 200),
            g.uniform(0.0, maze.height, 200),
            g.uniform(-math.pi, math.pi, 200),
        ]
    )
    quarter = maze.cell_size / 4
    lattice = np.column_stack(
        [
            g.integers(0, round(maze.width / quarter), 200) * quarter,
            g.integers(0, round(maze.height / quarter), 200) * quarter,
            g.integers(-4, 4, 200) * (math.pi / 4),
        ]
    )
    for poses in (uniform, lattice):
        ref = ~body_hits_wall(maze, poses, params) & ~whisker_bits(maze, poses, params).any(axis=1)
        got = clear_of_walls(maze, poses, params)
        assert got.dtype == np.bool_ and got.shape == (200,)
        assert np.array_equal(got, ref)
    assert ref.any() and not ref.all()  # both outcomes are exercised


def test_clear_of_walls_examples_and_bad_arguments() -> None:
    # arena: inner faces at 0.1 and 1.9; a body in the middle is clear, one across a wall is not
    poses = np.array([[1.0, 1.0, 0.0], [0.1, 1.0, 0.0], [1.9 - 0.0825 - 0.049, 1.0, 0.0]])
    assert clear_of_walls(ARENA, poses).tolist() == [True, False, False]  # last: whisker
    assert clear_of_walls(ARENA, poses[2:], World(whisker_range=0.04)).tolist() == [True]
    assert clear_of_walls(ARENA, np.empty((0, 3))).shape == (0,)
    with pytest.raises(ValueError, match="poses must be"):
        clear_of_walls(ARENA, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="finite"):
        clear_of_walls(ARENA, np.array([[1.0, math.nan, 0.0]]))


def test_read_only_inputs_give_the_same_bits_without_a_new_compilation() -> None:
    # start_poses and draw_gap hand out read-only cached arrays: numba would type them as a
    # different array type and compile the whole kernel again
    spec = PRESETS["paper-best"]
    maze = load_maze("paper")
    poses, gap = start_poses(maze, 4, 0, 6), draw_gap(4, 0, 6)
    assert not poses.flags.writeable and not gap.motor_gain.flags.writeable
    weights = np.random.default_rng(2).normal(0.0, 1.5, (6, spec.weight_count))
    copied = Gap(gap.whisker_range.copy(), gap.motor_gain.copy())
    first = simulate(spec, weights, maze, poses.copy(), 30, gap=copied)
    kernel: Any = _episode_kernel(spec)  # a numba dispatcher
    compiled = len(kernel.signatures)
    weights.flags.writeable = False
    again = simulate(spec, weights, maze, poses, 30, gap=gap)
    assert len(kernel.signatures) == compiled
    assert again.components.tobytes() == first.components.tobytes()
    assert again.poses_final.tobytes() == first.poses_final.tobytes()


def test_diverging_linear_feedback_never_puts_nan_in_poses_or_motors() -> None:
    """Fed-back linear outputs that overflow under the unbounded Eq 2 (inf, then NaN, after
    about 570 steps) saturate: 2,500 steps later every pose and motor command is finite."""
    maze = load_maze("paper")
    g = np.random.default_rng(23)
    spin = np.zeros((1, FLIP.weight_count))  # a(k) = [[4, .5], [.5, 4]] a(k-1) + [1, -1]
    spin[0, 5], spin[0, 11] = 1.0, -1.0
    spin[0, 12], spin[0, 13], spin[0, 15], spin[0, 16] = 4.0, 0.5, 0.5, 4.0
    weights = np.concatenate([spin, g.normal(0.0, 5.0, (11, FLIP.weight_count))])
    starts = np.tile(start_poses(maze, 4, 0, 4), (3, 1))
    gap = Gap(g.uniform(0.025, 0.1, 12), g.uniform(0.85, 1.15, (12, 2)))
    for run in (simulate, simulate_reference):
        res = run(FLIP, weights, maze, starts, 2500, gap=gap, record=True)
        assert res.poses is not None and res.motors is not None
        assert np.isfinite(res.poses).all() and np.isfinite(res.poses_final).all()
        assert np.isfinite(res.components).all()
        assert np.isfinite(res.motors).all() and np.abs(res.motors).max() <= 1.0
        assert (res.motors[0, 20:] == [1.0, -1.0]).all()  # saturated for good: it spins
        assert not res.stuck[0] and res.poses[0, -1, 2] != res.poses[0, 0, 2]


def step_gap(g: np.random.Generator, batch: int, steps: int) -> Gap:
    """The "step" gap model's shapes: a trigger distance per robot, step and whisker."""
    return Gap(g.uniform(0.025, 0.1, (batch, steps, 5)), g.uniform(0.85, 1.15, (batch, 2)))


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), preset=st.sampled_from(["paper-best", "recurrent-small"]))
def test_kernel_agrees_with_reference_under_per_step_whisker_ranges(seed: int, preset: str) -> None:
    spec = PRESETS[preset]
    maze = load_maze("paper")
    g = np.random.default_rng(seed)
    batch, steps = 16, 30
    weights = g.normal(0.0, 1.0, (batch, spec.weight_count))
    starts = np.tile(start_poses(maze, seed % 1000, 0, 8), (2, 1))
    gap = step_gap(g, batch, steps)
    fast = simulate(spec, weights, maze, starts, steps, gap=gap, record=True)
    ref = simulate_reference(spec, weights, maze, starts, steps, gap=gap, record=True)
    assert fast.poses is not None and ref.poses is not None
    assert fast.whiskers is not None and ref.whiskers is not None
    assert np.array_equal(fast.whiskers, ref.whiskers)
    assert np.array_equal(fast.stuck_step, ref.stuck_step)
    assert np.allclose(fast.poses, ref.poses, atol=1e-9)
    assert np.allclose(fast.components, ref.components, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(
    x=st.floats(-0.1, 2.5),
    y=st.floats(-0.1, 2.5),
    th=st.floats(-math.pi, math.pi),
    ranges=st.lists(st.floats(0.0, 0.1), min_size=5, max_size=5),
)
def test_kernel_whiskers_of_unequal_lengths_match_reference_anywhere(
    x: float, y: float, th: float, ranges: list[float]
) -> None:
    # the early out near the centre must hold for the longest whisker of the step
    maze = load_maze("paper")
    poses = np.array([[x, y, th]])
    ref = whisker_bits(maze, poses, ranges=np.array([ranges]))
    gap = Gap(np.array([[ranges]]), np.ones((1, 2)))
    res = simulate(CONST, const_weights(0, 0), maze, poses, 1, gap=gap, record=True)
    assert res.whiskers is not None
    assert np.array_equal(res.whiskers[:, 0], ref)


def test_per_step_ranges_are_read_each_step_and_per_whisker() -> None:
    # robot 0 faces a wall 60 mm beyond its whisker tips; robot 1 stands in the open, 0.8 m
    # from the nearest wall: only its long whiskers feel one, and the early out near its
    # centre must allow for the longest of the five
    poses = np.array([[1.9 - 0.0825 - 0.06, 1.0, 0.0], [1.0, 1.0, 0.0]])
    ranges = np.full((2, 3, 5), 0.01)
    ranges[0, 1, 2] = 0.08  # step 2, middle whisker: reaches the wall ahead
    ranges[0, 2, 0] = 0.5  # step 3, left whisker: reaches it at 60 degrees
    ranges[1, 1, 2] = 0.85
    ranges[1, 2, 4] = 0.99  # right whisker: reaches the wall below
    gap = Gap(ranges, np.ones((2, 2)))
    res = simulate(CONST, const_weights(0, 0, 2), ARENA, poses, 3, gap=gap, record=True)
    assert res.whiskers is not None
    assert res.whiskers.tolist() == [
        [[0, 0, 0, 0, 0], [0, 0, 1, 0, 0], [1, 0, 0, 0, 0]],
        [[0, 0, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 0, 0, 1]],
    ]
    ref = simulate_reference(CONST, const_weights(0, 0, 2), ARENA, poses, 3, gap=gap, record=True)
    assert ref.whiskers is not None and np.array_equal(ref.whiskers, res.whiskers)


def test_constant_per_step_ranges_are_the_trial_model_bit_for_bit() -> None:
    spec = PRESETS["paper-best"]
    maze = load_maze("paper")
    g = np.random.default_rng(3)
    weights = g.normal(0.0, 1.5, (24, spec.weight_count))
    starts = np.tile(start_poses(maze, 5, 0, 8), (3, 1))
    trial = Gap(g.uniform(0.025, 0.1, 24), g.uniform(0.85, 1.15, (24, 2)))
    step = Gap(np.repeat(trial.whisker_range, 40 * 5).reshape(24, 40, 5), trial.motor_gain)
    for run in (simulate, simulate_reference):
        a = run(spec, weights, maze, starts, 40, gap=trial, record=True)
        b = run(spec, weights, maze, starts, 40, gap=step, record=True)
        assert a.whiskers is not None and a.whiskers.any()
        for name in ("poses_final", "curve_length", "stuck_step", "poses", "whiskers", "motors"):
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), cut=st.integers(1, 19))
def test_per_step_gap_results_do_not_depend_on_batch(seed: int, cut: int) -> None:
    spec = PRESETS["paper-best"]
    maze = load_maze("paper")
    g = np.random.default_rng(seed)
    weights = g.normal(0.0, 1.5, (20, spec.weight_count))
    starts = np.tile(start_poses(maze, 0, 0, 4), (5, 1))
    gap = step_gap(g, 20, 40)
    whole = simulate(spec, weights, maze, starts, 40, gap=gap)
    parts = [
        simulate(
            spec,
            weights[a:b],
            maze,
            starts[a:b],
            40,
            gap=Gap(gap.whisker_range[a:b], gap.motor_gain[a:b]),
        )
        for a, b in ((0, cut), (cut, 20))
    ]
    assert whole.components.tobytes() == np.concatenate([p.components for p in parts]).tobytes()
    assert whole.poses_final.tobytes() == np.concatenate([p.poses_final for p in parts]).tobytes()


def test_per_step_gap_shapes_are_checked() -> None:
    spec = PRESETS["paper-best"]
    w = np.zeros((2, spec.weight_count))
    poses = np.tile([[1.0, 1.0, 0.0]], (2, 1))
    for ranges in (np.full((2, 4, 5), 0.05), np.full((2, 5, 4), 0.05), np.full((2, 4), 0.05)):
        with pytest.raises(ValueError, match="gap must hold"):
            simulate(spec, w, ARENA, poses, 5, gap=Gap(ranges, np.ones((2, 2))))
    with pytest.raises(ValueError, match="gap values"):
        simulate(spec, w, ARENA, poses, 5, gap=Gap(np.full((2, 5, 5), -0.01), np.ones((2, 2))))
    with pytest.raises(ValueError, match="ranges"):
        whisker_bits(ARENA, poses, ranges=np.full((2, 3), 0.05))
    assert simulate(
        spec, w, ARENA, poses, 0, gap=Gap(np.empty((2, 0, 5)), np.ones((2, 2)))
    ).stuck.shape == (2,)


def test_a_robot_gets_the_same_bits_in_any_lane_and_after_any_refill() -> None:
    """Permuting a batch moves every robot to another lane and tile, next to other robots,
    with lanes refilled at other times (stuck robots leave early): each result is unchanged."""
    spec = PRESETS["paper-best"]
    maze = load_maze("paper")
    weights = np.random.default_rng(5).normal(0.0, 1.5, size=(37, spec.weight_count))
    starts = np.resize(start_poses(maze, 0, 0, 64), (37, 3))
    whole = simulate(spec, weights, maze, starts, 60)
    assert 0.1 < whole.stuck.mean() < 0.9  # lanes do free up at different steps
    order = np.random.default_rng(6).permutation(37)
    moved = simulate(spec, weights[order], maze, starts[order], 60)
    assert moved.components.tobytes() == whole.components[order].tobytes()
    assert moved.poses_final.tobytes() == whole.poses_final[order].tobytes()
    assert moved.stuck_step.tobytes() == whole.stuck_step[order].tobytes()


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.floats(-8.0, 8.0),
            st.floats(-1e9, 1e9),
            st.sampled_from([0.0, -0.0, math.pi, -math.pi, math.pi / 4, 1e8, -1e8, 1.5e8]),
        ),
        min_size=network.LANES,
        max_size=network.LANES,
    )
)
def test_sincos_tile_is_sincos_bit_for_bit_and_within_an_ulp_of_libm(angles: list[float]) -> None:
    x = np.array(angles)
    c, s = np.empty(network.LANES), np.empty(network.LANES)
    _sincos_lanes(x, c, s)
    for k, angle in enumerate(angles):
        cos, sin = _sincos(angle)
        if abs(angle) <= SINCOS_LIMIT:  # beyond it the tile's lanes are the caller's to fix
            assert (c[k], s[k]) == (cos, sin)
        if abs(angle) <= 8.0:  # the simulator's angles: headings in [-pi, pi) plus a turn
            assert abs(cos - math.cos(angle)) <= 2.3e-16
            assert abs(sin - math.sin(angle)) <= 2.3e-16


@njit
def _sincos_lanes(x: np.ndarray, c: np.ndarray, s: np.ndarray) -> None:
    _sincos_tile(x, c, s)  # type: ignore[call-arg]  # numba supplies typingctx


PINNED = "fcd04b30"
"""sha256 (first 8 hex) of `test_simulate_bits_are_pinned`'s results: the fixed arithmetic
(polynomial exp, sin and cos, no libm in the step) gives these bits on any machine."""


def test_simulate_bits_are_pinned() -> None:
    spec = PRESETS["paper-best"]
    maze = load_maze("paper")
    weights = np.random.default_rng(7).normal(0.0, 1.5, size=(24, spec.weight_count))
    starts = start_poses(maze, 0, 0, 24)
    res = simulate(spec, weights, maze, starts, 100, World(stuck_after=10**6), record=True)
    assert res.poses is not None and res.motors is not None and res.cells is not None
    digest = hashlib.sha256()
    for part in (res.poses, res.motors, res.components, res.cells):
        digest.update(np.ascontiguousarray(part).tobytes())
    assert digest.hexdigest()[:8] == PINNED


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    ranges=st.lists(st.floats(0.0, 0.15), min_size=5, max_size=5),
)
def test_start_poses_keep_every_whisker_of_its_own_length_clear(
    seed: int, ranges: list[float]
) -> None:
    # the compiled start-pose test reads each whisker's nominal range, as whisker_bits does
    world = World(whisker_range=tuple(ranges))
    maze = load_maze("paper")
    g = np.random.default_rng(seed)
    poses = np.column_stack([g.uniform(0, 2, 200), g.uniform(0, 2, 200), g.uniform(-3, 3, 200)])
    expected = ~body_hits_wall(maze, poses, world) & ~whisker_bits(maze, poses, world).any(axis=1)
    assert np.array_equal(clear_of_walls(maze, poses, world), expected)
