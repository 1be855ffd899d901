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
from evorobotics.explore import confined
from evorobotics.maze import load_maze
from evorobotics.seeds import Purpose
from evorobotics.sim import Gap, simulate
from schemas.network import NetworkSpec
from schemas.world import N_WHISKERS, World

WHISKER_RANGES = (0.025, 0.0375, 0.05, 0.0625, 0.075, 0.0875, 0.1)
"""Whisker trigger distances in m: the paper's measured 25-100 mm in seven steps."""
GAIN_RATIOS = (0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15)
"""Left/right wheel gain ratios: the paper's 15 % either way."""
MAX_ROBOT_STEPS = 20_000_000
"""Upper bound on cells x poses x steps of one map (a row is recorded at a time)."""


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
    world = world or World()
    cells = len(WHISKER_RANGES) * len(GAIN_RATIOS)
    if poses < 1 or steps < 1:
        raise ValueError(f"poses and steps must be >= 1, got {poses} and {steps}")
    if cells * poses * steps > MAX_ROBOT_STEPS:
        raise ValueError(
            f"{cells} cells x {poses} poses x {steps} steps exceeds the limit of "
            f"{MAX_ROBOT_STEPS} robot steps"
        )
    loaded = load_maze(maze)
    starts = start_poses(loaded, seed, 0, poses, world, Purpose.ROBUSTNESS)
    w = np.repeat(np.asarray(weights, dtype=np.float64).reshape(1, -1), poses, axis=0)
    n_ratios = len(GAIN_RATIOS)

    def row(i: int) -> tuple[list[float], list[float]]:
        batch = n_ratios * poses
        ranges = np.full((batch, N_WHISKERS), WHISKER_RANGES[i])
        gains = np.repeat(np.stack([wheel_gains(r, world) for r in GAIN_RATIOS]), poses, axis=0)
        run = simulate(
            spec,
            np.tile(w, (n_ratios, 1)),
            loaded,
            np.tile(starts, (n_ratios, 1)),
            steps,
            params=world,
            gap=Gap(ranges, gains),
            record=True,
        )
        assert run.poses is not None
        roams = (~confined(run.poses, run.stuck_step) & ~run.stuck).reshape(n_ratios, poses)
        stuck = run.stuck.reshape(n_ratios, poses)
        return roams.mean(axis=1).tolist(), stuck.mean(axis=1).tolist()

    rows = map_slices(
        lambda a, b: [row(i) for i in range(a, b)],
        [(i, i + 1) for i in range(len(WHISKER_RANGES))],
        threads,
    )
    flat = [r for part in rows for r in part]
    return RobustnessMap(
        maze=loaded.name,
        poses=poses,
        steps=steps,
        seed=seed,
        whisker_ranges=list(WHISKER_RANGES),
        gain_ratios=list(GAIN_RATIOS),
        roaming=[r for r, _ in flat],
        stuck=[s for _, s in flat],
    )
