"""The exploration report (evorobotics.explore) against its definitions, on built and simulated
paths: confinement against a brute-force reference, stuck horizons, coverage, Eq 12 at 40; the
kernel's watched measures against the same definitions on the recorded paths, bit for bit."""

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
    trials,
    watch,
    watched_trials,
)
from evorobotics.fitness import fitness
from evorobotics.maze import load_maze
from evorobotics.seeds import Purpose
from evorobotics.sim import Gap, SimResult, simulate, simulate_watched
from schemas.network import PRESETS
from schemas.run import FitnessWeights
from schemas.world import World

REACTIVE = PRESETS["reactive"]


def recorded(poses: np.ndarray, stuck_step: np.ndarray) -> SimResult:
    """A SimResult holding a built path (B, n+1, 3): what `report` reads of a simulation."""
    b = poses.shape[0]
    zeros = np.zeros(b)
    return SimResult(poses[:, -1], zeros, zeros, zeros, stuck_step, poses=poses)


def confined_reference(
    path: np.ndarray,
    stuck_step: int,
    steps: int = CONFINED_STEPS,
    diagonal: float = CONFINED_DIAGONAL,
) -> bool:
    """The definition, one window at a time: `steps` consecutive steps, all before the step
    the robot stuck on, whose positions fit a box of diagonal <= `diagonal`."""
    n = path.shape[0]  # positions: before step 1 ... after step n - 1
    for first in range(n - steps):
        last = first + steps  # position after the window's last step
        if stuck_step >= 0 and last >= stuck_step:
            break
        window = path[first : last + 1, :2]
        dx, dy = window.max(axis=0) - window.min(axis=0)
        if np.hypot(dx, dy) <= diagonal:
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


def random_trials(
    maze: str, seed: int, n: int, world: World, gap: bool
) -> tuple[np.ndarray, np.ndarray, Gap | None]:
    """n random reactive controllers (some spin, some stick, some roam), start poses, draws."""
    g = np.random.default_rng(seed)
    weights = g.uniform(-3.0, 3.0, (n, REACTIVE.weight_count))
    starts = start_poses(load_maze(maze), seed, 0, n, world)
    drawn = Gap(g.uniform(0.025, 0.1, (n, 5)), g.uniform(0.85, 1.15, (n, 2))) if gap else None
    return weights, starts, drawn


@settings(max_examples=40, deadline=None)
@given(
    maze=st.sampled_from(["paper", "arena", "corridor", "gen:4:2"]),
    seed=st.integers(0, 2**16),
    steps=st.integers(1, 400),
    stuck_after=st.sampled_from([1, 3, 10**6]),
    gap=st.booleans(),
)
def test_watched_trials_are_the_recorded_trials_bit_for_bit(
    maze: str, seed: int, steps: int, stuck_after: int, gap: bool
) -> None:
    world = World(stuck_after=stuck_after)
    weights, starts, drawn = random_trials(maze, seed, 24, world, gap)
    loaded = load_maze(maze)
    recorded = simulate(REACTIVE, weights, loaded, starts, steps, world, drawn, record=True)
    watched = watch(REACTIVE, weights, loaded, starts, steps, world, drawn)
    assert watched_trials(watched).tobytes() == trials(recorded, steps).tobytes()
    assert watched.components.tobytes() == recorded.components.tobytes()


def test_watched_trials_meet_every_outcome() -> None:
    # what the property test above compares: confined, stuck and roaming trials alike
    world = World(stuck_after=3)
    weights, starts, _ = random_trials("paper", 1, 200, world, False)
    rows = watched_trials(watch(REACTIVE, weights, load_maze("paper"), starts, 400, world))
    stuck, near = rows[:, 0] >= 0, rows[:, 1] == 1.0
    assert stuck.any() and near.any() and (~stuck & ~near).any() and (stuck & near).any()


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    steps=st.integers(1, 250),
    window=st.integers(1, 40),
    diagonal=st.floats(0.0, 0.6),
    cell=st.sampled_from([0.05, 0.1, 0.3]),
    stuck_after=st.sampled_from([1, 3]),
    data=st.data(),
)
def test_simulate_watched_measures_its_definitions_on_the_recorded_paths(
    seed: int,
    steps: int,
    window: int,
    diagonal: float,
    cell: float,
    stuck_after: int,
    data: st.DataObject,
) -> None:
    horizon = data.draw(st.integers(1, steps))
    world = World(stuck_after=stuck_after)
    maze = load_maze("paper")
    weights, starts, drawn = random_trials("paper", seed, 16, world, True)
    rec = simulate(REACTIVE, weights, maze, starts, steps, world, drawn, record=True)
    got = simulate_watched(
        REACTIVE, weights, maze, starts, steps, world, drawn,
        window=window, diagonal=diagonal, cell=cell, horizon=horizon,
    )  # fmt: skip
    assert rec.poses is not None
    assert got.stuck_step.tolist() == rec.stuck_step.tolist()
    for i, path in enumerate(rec.poses[:, :, :2]):
        stuck = int(rec.stuck_step[i])
        assert got.confined[i] == confined_reference(rec.poses[i], stuck, window, diagonal)
        assert got.coverage[i] == len({tuple(c) for c in np.floor(path / cell).tolist()})
        offsets = np.hypot(*(path - path[0]).T)
        assert got.horizon_offset[i] == offsets[: horizon + 1].max()
        assert got.farthest[i] == offsets.max()
        assert got.horizon_net[i] == offsets[horizon]
        assert got.moves[i].tolist() == np.hypot(*np.diff(path[: horizon + 1], axis=0).T).tolist()


def test_simulate_watched_refuses_bad_arguments() -> None:
    maze = load_maze("paper")
    weights, starts, _ = random_trials("paper", 0, 2, World(), False)

    def run(starts: np.ndarray, horizon: int) -> None:
        simulate_watched(
            REACTIVE, weights, maze, starts, 10,
            window=CONFINED_STEPS, diagonal=CONFINED_DIAGONAL, cell=COVERAGE_CELL, horizon=horizon,
        )  # fmt: skip

    for horizon in (0, 11):
        with pytest.raises(ValueError, match="horizon"):
            run(starts, horizon)
    outside = starts.copy()
    outside[1, 0] = -0.5
    with pytest.raises(ValueError, match="inside the maze"):
        run(outside, 5)


def test_a_report_is_the_same_on_any_number_of_threads() -> None:
    weights = np.random.default_rng(8).uniform(-1.0, 1.0, REACTIVE.weight_count)
    one = explore(REACTIVE, weights, poses=45, steps=150, seed=2, reality_gap=True)
    assert (
        explore(REACTIVE, weights, poses=45, steps=150, seed=2, reality_gap=True, threads=3) == one
    )
