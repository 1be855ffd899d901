"""A controller's robustness map: how it roams across the paper's reality gap, cell by cell.

The gap (paper section 4) has two axes a lab can see on its robots: how far the whiskers
trigger and how unequal the two motors are. The map fixes both per cell, every whisker at one
range and the wheels at one left/right gain ratio (left = sqrt(ratio), right = 1/sqrt(ratio),
times the world's `motor_gain`, so the mean speed stays), and runs the same unseen start poses
(rng(seed, 0, Purpose.ROBUSTNESS)) in every cell: cells differ by the physics only.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from evorobotics.evaluate import map_slices, start_poses
from evorobotics.explore import watch
from evorobotics.maze import load_maze
from evorobotics.seeds import Purpose
from evorobotics.sim import Gap
from schemas.network import NetworkSpec
from schemas.wire import REPORT_ROBOT_STEPS
from schemas.world import N_WHISKERS, World

WHISKER_RANGES = (0.025, 0.0375, 0.05, 0.0625, 0.075, 0.0875, 0.1)
"""Whisker trigger distances in m: the paper's measured 25-100 mm in seven steps."""
GAIN_RATIOS = (0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15)
"""Left/right wheel gain ratios: the paper's 15 % either way."""
CELLS = len(WHISKER_RANGES) * len(GAIN_RATIOS)
"""Cells of a map: 49."""
MAX_ROBOT_STEPS = REPORT_ROBOT_STEPS
"""Upper bound on cells x poses x steps of one map."""


@dataclass(frozen=True)
class RobustnessMap:
    """Fractions of trials per cell, indexed [whisker range][gain ratio]."""

    maze: str
    poses: int
    steps: int
    seed: int
    whisker_ranges: list[float]
    gain_ratios: list[float]
    roaming: list[list[float]]
    stuck: list[list[float]]

    def as_dict(self) -> dict[str, object]:
        return asdict(self)

    @property
    def worst_roaming(self) -> float:
        return min(min(row) for row in self.roaming)


def wheel_gains(ratio: float, world: World) -> np.ndarray:
    """(2,) gains of one cell: the ratio split evenly between the wheels, around the world's."""
    half = float(np.sqrt(ratio))
    left, right = world.motor_gain
    return np.array([left * half, right / half])


def check_size(poses: int, steps: int) -> None:
    """ValueError unless 1 <= poses, steps and CELLS x poses x steps <= MAX_ROBOT_STEPS."""
    if poses < 1 or steps < 1:
        raise ValueError(f"poses and steps must be >= 1, got {poses} and {steps}")
    if CELLS * poses * steps > MAX_ROBOT_STEPS:
        raise ValueError(
            f"{CELLS} cells x {poses} poses x {steps} steps exceeds the limit of "
            f"{MAX_ROBOT_STEPS} robot steps"
        )


def map_trials(
    spec: NetworkSpec,
    weights: np.ndarray,
    start: int,
    stop: int,
    *,
    poses: int,
    steps: int,
    maze: str,
    seed: int,
    world: World,
) -> np.ndarray:
    """(stop - start, 2) float64: trials start:stop of the map, each roaming and stuck (0 or
    1). Trial t is pose t % poses in cell t // poses (whisker range cell // 7, gain ratio
    cell % 7); a row depends on its trial alone, so any slices concatenate to the map's."""
    check_size(poses, steps)
    if not 0 <= start < stop <= CELLS * poses:
        raise ValueError(f"trials {start}:{stop} outside the map's {CELLS * poses}")
    loaded = load_maze(maze)
    starts = start_poses(loaded, seed, 0, poses, world, Purpose.ROBUSTNESS)
    t = np.arange(start, stop)
    cell, pose = t // poses, t % poses
    ratios = np.stack([wheel_gains(r, world) for r in GAIN_RATIOS])
    ranges = np.repeat(np.array(WHISKER_RANGES)[cell // len(GAIN_RATIOS), None], N_WHISKERS, 1)
    w = np.asarray(weights, dtype=np.float64).reshape(1, -1)
    gap = Gap(ranges, ratios[cell % len(GAIN_RATIOS)])
    run = watch(spec, np.repeat(w, stop - start, axis=0), loaded, starts[pose], steps, world, gap)
    roams = ~run.confined & ~run.stuck
    return np.stack([roams, run.stuck], axis=1).astype(np.float64)


def robustness(
    spec: NetworkSpec,
    weights: np.ndarray,
    *,
    poses: int = 50,
    steps: int = 1000,
    maze: str = "paper",
    seed: int = 0,
    world: World | None = None,
    threads: int = 1,
) -> RobustnessMap:
    """The map over WHISKER_RANGES x GAIN_RATIOS, one trial per pose and cell, a row of cells
    per slice on `threads` threads (the same figures whatever the count)."""
    check_size(poses, steps)
    world = world or World()
    per_row = len(GAIN_RATIOS) * poses
    rows = map_slices(
        lambda a, b: map_trials(
            spec, weights, a, b, poses=poses, steps=steps, maze=maze, seed=seed, world=world
        ),
        [(i * per_row, (i + 1) * per_row) for i in range(len(WHISKER_RANGES))],
        threads,
    )
    return robustness_map(np.concatenate(rows), poses, steps, maze, seed)


def robustness_map(rows: np.ndarray, poses: int, steps: int, maze: str, seed: int) -> RobustnessMap:
    """The map from the rows of all its trials (`map_trials` of every trial, in order,
    wherever they were simulated): `robustness`'s, bit for bit."""
    if rows.shape != (CELLS * poses, 2):
        raise ValueError(f"rows {rows.shape} are not the map's {CELLS * poses} trials x 2")
    grid = rows.reshape(len(WHISKER_RANGES), len(GAIN_RATIOS), poses, 2).mean(axis=2)
    return RobustnessMap(
        maze=load_maze(maze).name,
        poses=poses,
        steps=steps,
        seed=seed,
        whisker_ranges=list(WHISKER_RANGES),
        gain_ratios=list(GAIN_RATIOS),
        roaming=grid[..., 0].tolist(),
        stuck=grid[..., 1].tolist(),
    )
