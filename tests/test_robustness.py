"""The robustness map: every cell is the same unseen poses under that cell's physics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.evaluate import start_poses
from evorobotics.explore import confined
from evorobotics.maze import load_maze
from evorobotics.robustness import (
    GAIN_RATIOS,
    MAX_ROBOT_STEPS,
    WHISKER_RANGES,
    RobustnessMap,
    robustness,
    wheel_gains,
)
from evorobotics.seeds import Purpose
from evorobotics.sim import Gap, simulate
from schemas.network import PRESETS
from schemas.world import World

SPEC = PRESETS["reactive"]
WEIGHTS = np.random.default_rng(4).uniform(-1.0, 1.0, SPEC.weight_count)
WORLD = World(motor_gain=(0.95, 1.05))


@pytest.fixture(scope="module")
def small_map() -> RobustnessMap:
    return robustness(SPEC, WEIGHTS, poses=6, steps=120, seed=3, world=WORLD)


@settings(max_examples=10, deadline=None)
@given(i=st.integers(0, len(WHISKER_RANGES) - 1), j=st.integers(0, len(GAIN_RATIOS) - 1))
def test_a_cell_is_the_unseen_poses_under_its_whiskers_and_gains(
    small_map: RobustnessMap, i: int, j: int
) -> None:
    maze = load_maze("paper")
    poses = start_poses(maze, 3, 0, 6, WORLD, Purpose.ROBUSTNESS)
    gains = np.tile(wheel_gains(GAIN_RATIOS[j], WORLD), (6, 1))
    gap = Gap(np.full((6, 5), WHISKER_RANGES[i]), gains)
    w = np.repeat(WEIGHTS[None], 6, axis=0)
    run = simulate(SPEC, w, maze, poses, 120, WORLD, gap, record=True)
    assert run.poses is not None
    roaming = ~confined(run.poses, run.stuck_step) & ~run.stuck
    assert small_map.roaming[i][j] == roaming.mean()
    assert small_map.stuck[i][j] == run.stuck.mean()


def test_the_map_is_the_same_on_any_threads_and_differs_by_seed(small_map: RobustnessMap) -> None:
    on_two = robustness(SPEC, WEIGHTS, poses=6, steps=120, seed=3, world=WORLD, threads=2)
    assert on_two == small_map
    assert robustness(SPEC, WEIGHTS, poses=6, steps=120, seed=4, world=WORLD) != small_map
    assert on_two.as_dict()["whisker_ranges"] == list(WHISKER_RANGES)
    assert len(on_two.roaming) == len(WHISKER_RANGES)
    assert all(len(row) == len(GAIN_RATIOS) for row in on_two.stuck)


@given(ratio=st.floats(0.5, 2.0), left=st.floats(0.5, 1.5), right=st.floats(0.5, 1.5))
def test_wheel_gains_split_the_ratio_around_the_worlds_gains(
    ratio: float, left: float, right: float
) -> None:
    gains = wheel_gains(ratio, World(motor_gain=(left, right)))
    assert gains[0] / gains[1] == pytest.approx(ratio * left / right)
    assert gains[0] * gains[1] == pytest.approx(left * right)
    assert math.isclose(wheel_gains(1.0, World())[0], 1.0)


def test_bad_sizes_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match="poses and steps"):
        robustness(SPEC, WEIGHTS, poses=0)
    cells = len(WHISKER_RANGES) * len(GAIN_RATIOS)
    with pytest.raises(ValueError, match="exceeds the limit"):
        robustness(SPEC, WEIGHTS, poses=MAX_ROBOT_STEPS // cells + 1, steps=1)
