"""The exploration report (evorobotics.explore) against its definitions, on built and simulated
paths: confinement against a brute-force reference, stuck horizons, coverage, Eq 12 at 40."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.evaluate import draw_gap, start_poses
from evorobotics.explore import (
    CONFINED_DIAGONAL,
    CONFINED_STEPS,
    COVERAGE_CELL,
    HORIZONS,
    PAPER_TRIAL,
    confined,
    explore,
    report,
)
from evorobotics.fitness import fitness
from evorobotics.maze import load_maze
from evorobotics.seeds import Purpose
from evorobotics.sim import Gap, SimResult, simulate
from schemas.network import PRESETS
from schemas.run import FitnessWeights
from schemas.world import World

REACTIVE = PRESETS["reactive"]


def recorded(poses: np.ndarray, stuck_step: np.ndarray) -> SimResult:
    """A SimResult holding a built path (B, n+1, 3): what `report` reads of a simulation."""
    b = poses.shape[0]
    zeros = np.zeros(b)
    return SimResult(poses[:, -1], zeros, zeros, zeros, stuck_step, poses=poses)


def confined_reference(path: np.ndarray, stuck_step: int) -> bool:
    """The definition, one window at a time: CONFINED_STEPS consecutive steps, all before the
    step the robot stuck on, whose positions fit a box of diagonal <= CONFINED_DIAGONAL."""
    n = path.shape[0]  # positions: before step 1 ... after step n - 1
    for first in range(n - CONFINED_STEPS):
        last = first + CONFINED_STEPS  # position after the window's last step
        if stuck_step >= 0 and last >= stuck_step:
            break
        window = path[first : last + 1, :2]
        dx, dy = window.max(axis=0) - window.min(axis=0)
        if np.hypot(dx, dy) <= CONFINED_DIAGONAL:
            return True
    return False


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    robots=st.integers(1, 4),
    steps=st.integers(CONFINED_STEPS - 5, 3 * CONFINED_STEPS),
    stride=st.sampled_from([0.0, 0.002, 0.004, 0.01, 0.03]),
    data=st.data(),
)
def test_confined_matches_a_brute_force_reference(
    seed: int, robots: int, steps: int, stride: float, data: st.DataObject
) -> None:
    rng = np.random.default_rng(seed)
    # random walks whose step sizes also vary along the path: some windows fit the box, some not
    scale = stride * rng.uniform(0.0, 2.0, (robots, 1, 1)) * rng.uniform(0.0, 2.0, (1, steps, 1))
    moves = rng.normal(0.0, 1.0, (robots, steps, 3)) * scale
    poses = np.concatenate([np.full((robots, 1, 3), 1.0), 1.0 + np.cumsum(moves, axis=1)], axis=1)
    stuck = np.array(data.draw(st.lists(st.integers(-1, steps), min_size=robots, max_size=robots)))
    stuck[stuck == 0] = -1  # steps are 1-based: 0 is no step
    got = confined(poses, stuck)
    want = [confined_reference(poses[i], int(stuck[i])) for i in range(robots)]
    assert got.tolist() == want


def test_confined_sees_a_box_exactly_at_the_limit_and_just_over() -> None:
    """Back and forth along a line of length L: confined iff L <= CONFINED_DIAGONAL."""
    n = 2 * CONFINED_STEPS
    for length, want in ((CONFINED_DIAGONAL, True), (CONFINED_DIAGONAL * 1.001, False)):
        x = np.where(np.arange(n + 1) % 2 == 0, 0.0, length)  # extent exactly `length`
        poses = np.stack([x, np.full(n + 1, 0.5), np.zeros(n + 1)], axis=-1)[None]
        assert confined(poses, np.array([-1])).tolist() == [want]


def test_a_robot_that_never_moves_is_confined_not_roaming() -> None:
    still = np.zeros(REACTIVE.weight_count)  # every output 0.5: both wheels at command 0
    e = explore(REACTIVE, still, poses=20, steps=CONFINED_STEPS + 20, seed=1)
    assert e.confined == 1.0 and e.roaming == 0.0
    assert all(v == 0.0 for v in e.stuck.values())
    assert all(v == 0.0 for v in e.max_offset.values())
    assert e.coverage == 1.0


@settings(max_examples=60, deadline=None)
@given(steps=st.integers(1, 400), data=st.data())
def test_a_robot_stuck_at_step_s_is_stuck_from_horizon_s_on(
    steps: int, data: st.DataObject
) -> None:
    s = data.draw(st.integers(1, steps))
    poses = np.zeros((1, steps + 1, 3))
    poses[0, :, 0] = np.linspace(0.0, 0.01 * steps, steps + 1)  # moving: never confined
    r = report(recorded(poses, np.array([s])), FitnessWeights(), steps)
    assert set(r["stuck"]) == {h for h in (*HORIZONS, steps) if h <= steps}
    for h, fraction in r["stuck"].items():
        assert fraction == (1.0 if h >= s else 0.0), (h, s)
    assert r["roaming"] == 0.0
    never = report(recorded(poses, np.array([-1])), FitnessWeights(), steps)
    assert all(v == 0.0 for v in never["stuck"].values()) and never["roaming"] == 1.0


@settings(max_examples=60, deadline=None)
@given(
    x0=st.floats(0.0, 2.0),
    y0=st.floats(0.0, 2.0),
    stride=st.floats(0.001, 0.99 * COVERAGE_CELL),  # a stride of a whole cell may round past one
    steps=st.integers(1, 300),
)
def test_coverage_of_a_straight_line_counts_the_cells_it_crosses(
    x0: float, y0: float, stride: float, steps: int
) -> None:
    x = x0 + stride * np.arange(steps + 1)
    poses = np.stack([x, np.full(steps + 1, y0), np.zeros(steps + 1)], axis=-1)[None]
    r = report(recorded(poses, np.array([-1])), FitnessWeights(), steps)
    # steps no longer than a cell skip none: every cell from the first to the last is visited
    first, last = np.floor(x[[0, -1]] / COVERAGE_CELL)
    assert r["coverage"] == last - first + 1
    assert r["max_offset"][steps] == pytest.approx(x[-1] - x[0])


@pytest.mark.parametrize("gap", [False, True])
def test_fitness_40_is_eq_12_of_a_40_step_simulation_from_the_same_poses(gap: bool) -> None:
    rng = np.random.default_rng(7)
    weights = rng.uniform(-1.0, 1.0, REACTIVE.weight_count)
    world = World(stuck_after=2)
    poses, seed = 60, 5
    e = explore(REACTIVE, weights, poses=poses, steps=150, seed=seed, reality_gap=gap, world=world)
    maze = load_maze("paper")
    starts = start_poses(maze, seed, 0, poses, world, Purpose.EXPLORATION)
    drawn = draw_gap(seed, 0, poses, world, Purpose.EXPLORATION_GAP) if gap else None
    result = simulate(
        REACTIVE,
        np.repeat(weights[None, :], poses, axis=0),
        maze,
        starts,
        PAPER_TRIAL,
        params=world,
        gap=None if drawn is None else Gap(drawn.whisker_range.copy(), drawn.motor_gain.copy()),
    )
    assert 0 < result.stuck.sum() < poses  # both kinds of trial are compared
    want = float(np.mean(fitness(result.components, FitnessWeights())))
    assert e.fitness_40 == pytest.approx(want, rel=1e-9, abs=1e-9)
    assert e.max_offset[PAPER_TRIAL] == pytest.approx(float(np.mean(result.max_offset)))
    assert e.stuck[PAPER_TRIAL] == pytest.approx(float(np.mean(result.stuck)))


def test_a_report_is_a_pure_function_of_its_arguments() -> None:
    weights = np.random.default_rng(3).uniform(-1.0, 1.0, REACTIVE.weight_count)
    first = explore(REACTIVE, weights, poses=30, steps=120, seed=4)
    assert first == explore(REACTIVE, weights, poses=30, steps=120, seed=4)
    assert first != explore(REACTIVE, weights, poses=30, steps=120, seed=5)


def test_bad_sizes_are_refused() -> None:
    weights = np.zeros(REACTIVE.weight_count)
    for poses, steps in ((0, 10), (10, 0), (100_000, 1_000)):
        with pytest.raises(ValueError, match="poses"):
            explore(REACTIVE, weights, poses=poses, steps=steps)
