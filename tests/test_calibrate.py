"""Calibration: a robot's hidden whisker ranges and wheel gains fitted back from its traces."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from evorobotics.calibrate import (
    MAX_RANGE,
    MIN_SAMPLES,
    CalibrationError,
    calibrate,
    touch_distances,
)
from evorobotics.maze import load_maze
from evorobotics.sim import Gap
from robot_agent.sim_body import SimBody
from schemas.world import World

MAZE = load_maze("arena")


def drive(body: SimBody, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Traces of a robot wandering under random commands: ahead, and on contact (or a refused
    move) backing up then turning a random way for a random time."""
    gen = np.random.default_rng(seed)
    poses, bits, motors = [], [], []
    plan: list[tuple[float, float]] = []
    for _ in range(steps):
        felt = body.whiskers()
        poses.append(np.asarray(body.pose, dtype=np.float64).reshape(3))
        bits.append([int(b) for b in felt])
        if not plan and (any(felt) or body.blocked):
            turn = 0.6 if gen.random() < 0.5 else -0.6
            plan = [(-0.5, -0.5)] * 3 + [(-turn, turn)] * int(gen.integers(2, 12))
        if plan:
            m = plan.pop(0)
        else:
            ahead = float(gen.uniform(0.4, 1.0))
            m = (ahead, ahead * float(gen.uniform(0.9, 1.1)))
        motors.append(m)
        body.step(*m)
    return np.array(poses), np.array(bits), np.array(motors)


@settings(max_examples=12, deadline=None)
@example(ranges=[0.06, 0.05, 0.04, 0.07, 0.09], gains=(0.9, 1.12), seed=0)  # every whisker touches
@given(
    ranges=st.lists(st.floats(0.025, 0.1), min_size=5, max_size=5),
    gains=st.tuples(st.floats(0.85, 1.15), st.floats(0.85, 1.15)),
    seed=st.integers(0, 1000),
)
def test_hidden_physics_lie_within_the_fit_and_its_uncertainty(
    ranges: list[float], gains: tuple[float, float], seed: int
) -> None:
    world = World()
    start = np.array([[1.0, 1.0, 0.3]])
    body = SimBody(MAZE, start[0], Gap(np.array([ranges]), np.array([gains])), world)
    poses, bits, motors = drive(body, 1500, seed)
    # a short whisker beside long ones may never be the first to touch: bounded from above
    bounded = tuple(k for k in range(5) if len(np.unique(bits[:, k])) == 1)
    fit = calibrate(MAZE, poses, bits, motors, world)
    assert fit.bounded == bounded
    assert fit.motor_gain == pytest.approx(gains, abs=1e-9)
    assert fit.pose_residual_m < 1e-9
    for got, err, hidden in zip(
        fit.whisker_range, fit.whisker_range_uncertainty, ranges, strict=True
    ):
        assert abs(got - hidden) <= err + 1e-7
    assert fit.whisker_disagreements == (0,) * 5
    assert fit.samples == 1500 and set(fit.as_dict()) >= {"whisker_range", "uncertainty"}


def test_a_whisker_whose_bit_never_changed_is_bounded_by_the_walls_it_passed() -> None:
    world = World()
    body = SimBody(MAZE, np.array([1.0, 1.0, 0.0]), Gap(np.full((1, 5), 0.05), np.ones((1, 2))))
    poses, bits, motors = drive(body, 400, 1)
    assert bits[:, 2].any()
    bits[:, 2] = 0  # as if its range were shorter than any wall it came near
    fit = calibrate(MAZE, poses, bits, motors, world)
    nearest = float(touch_distances(MAZE, poses, world)[:, 2].min())
    assert fit.bounded == (2,) and fit.whisker_disagreements[2] == 0
    assert fit.whisker_range[2] == pytest.approx(nearest / 2)
    assert fit.whisker_range[2] + fit.whisker_range_uncertainty[2] == pytest.approx(nearest)
    assert fit.as_dict()["bounded"] == [2]
    bits[:, 2] = 1  # as if it reached beyond every wall it passed: bounded from below
    above = calibrate(MAZE, poses, bits, motors, world)
    farthest = float(np.minimum(touch_distances(MAZE, poses, world)[:, 2], MAX_RANGE).max())
    assert above.bounded == (2,)
    assert above.whisker_range[2] - above.whisker_range_uncertainty[2] == pytest.approx(farthest)
    assert above.whisker_range[2] + above.whisker_range_uncertainty[2] == pytest.approx(MAX_RANGE)


def test_steps_across_a_break_in_the_traces_are_not_fitted() -> None:
    world = World()
    body = SimBody(MAZE, np.array([1.0, 1.0, 0.0]), Gap(np.full((1, 5), 0.05), np.ones((1, 2))))
    poses, bits, motors = drive(body, 400, 3)
    poses[200:, :2] += 0.5  # a teleport: another agent start, elsewhere
    with pytest.raises(AssertionError):
        assert calibrate(MAZE, poses, bits, motors, world).pose_residual_m < 1e-9
    follows = np.ones(399, dtype=bool)
    follows[199] = False
    fit = calibrate(MAZE, poses, bits, motors, world, follows)
    assert fit.pose_residual_m < 1e-9 and fit.moving_steps <= 398


def test_too_little_or_uninformative_data_is_refused_by_name() -> None:
    world = World()
    still = np.tile([1.0, 1.0, 0.0], (MIN_SAMPLES, 1))
    none = np.zeros((MIN_SAMPLES, 5), dtype=int)
    idle = np.zeros((MIN_SAMPLES, 2))
    with pytest.raises(CalibrationError, match="at least"):
        calibrate(MAZE, still[:10], none[:10], idle[:10], world)
    with pytest.raises(CalibrationError, match="never moved"):
        calibrate(MAZE, still, none, idle, world)
    body = SimBody(MAZE, np.array([1.0, 1.0, 0.0]), Gap(np.full((1, 5), 0.05), np.ones((1, 2))))
    poses, bits, motors = drive(body, 200, 1)
    with pytest.raises(CalibrationError, match="non-finite"):
        calibrate(MAZE, poses * np.nan, bits, motors, world)


def test_traces_the_drive_model_cannot_explain_are_refused_by_name() -> None:
    """A fit that is not a robot's: one wheel never driven, or poses that move against the
    commands (a wheel wired backwards, another robot's poses). Nothing comes back to store."""
    world = World()
    body = SimBody(MAZE, np.array([1.0, 1.0, 0.0]), Gap(np.full((1, 5), 0.05), np.ones((1, 2))))
    poses, bits, motors = drive(body, 200, 1)
    one_wheel = motors.copy()
    one_wheel[:, 0] = 0.0
    with pytest.raises(CalibrationError, match="never drove one of the wheels"):
        calibrate(MAZE, poses, bits, one_wheel, world)
    with pytest.raises(CalibrationError, match="not positive"):
        calibrate(MAZE, poses, bits, -motors, world)
