"""The simulator's EvBot as the emulator's physics: one robot, stepped one dt at a time.

Uses exactly `evorobotics.sim`'s sensing (`whisker_bits`), motion (`move`) and collision
(`body_hits_wall`) on a batch of one. One difference from a simulated trial, on purpose: a
blocked move leaves the pose unchanged but does not freeze the robot for good (the simulator's
`stuck` ends a trial; a real EvBot pressed against a wall can still back away), and the body
records `blocked` so traces carry the ground truth the stuck detector is measured against.

The reality gap (paper section 4) is drawn once per robot from
rng(seed, 0, Purpose.REALITY_GAP, index): whisker trigger distance uniform in 25-100 mm, each
wheel's gain uniform within +/-15 %.
"""

from __future__ import annotations

import math

import numpy as np

from evorobotics.maze import Maze, load_maze
from evorobotics.seeds import Purpose, rng
from evorobotics.sim import Gap, WorldParams, body_hits_wall, move, whisker_bits

GAP_WHISKER_RANGE = (0.025, 0.100)
"""Metres: where a real whisker may trigger (paper section 4)."""
GAP_MOTOR = 0.15
"""Real motors within 15 % of simulated (paper section 4)."""
START_ATTEMPTS = 10_000


def draw_gap(seed: int, index: int) -> Gap:
    """The reality gap of robot `index` under `seed`: a batch-of-one Gap."""
    gen = rng(seed, 0, Purpose.REALITY_GAP, index)
    whisker = gen.uniform(*GAP_WHISKER_RANGE, size=1)
    gain = gen.uniform(1.0 - GAP_MOTOR, 1.0 + GAP_MOTOR, size=(1, 2))
    return Gap(whisker, gain)


def free_pose(maze: Maze, seed: int, index: int, params: WorldParams) -> np.ndarray:
    """A uniformly drawn (1, 3) pose whose body touches no wall."""
    gen = rng(seed, 0, Purpose.AGENT, index)
    for _ in range(START_ATTEMPTS):
        pose = np.array(
            [
                [
                    gen.uniform(0, maze.width),
                    gen.uniform(0, maze.height),
                    gen.uniform(-math.pi, math.pi),
                ]
            ]
        )
        if not body_hits_wall(maze, pose, params)[0]:
            return pose
    raise ValueError(f"no free start pose found in maze {maze.name!r}")


class SimBody:
    """One simulated EvBot: pose, gap, and whether its last move was blocked by a wall."""

    def __init__(
        self,
        maze: Maze,
        pose: np.ndarray,
        gap: Gap | None = None,
        params: WorldParams | None = None,
    ) -> None:
        self.params = params or WorldParams()
        self.maze = maze
        pose = np.asarray(pose, dtype=np.float64).reshape(1, 3)
        if body_hits_wall(maze, pose, self.params)[0]:
            raise ValueError(f"start pose {pose[0].tolist()} overlaps a wall")
        self.pose = pose
        self.gap = gap or Gap.nominal(1, self.params)
        if self.gap.whisker_range.shape != (1,) or self.gap.motor_gain.shape != (1, 2):
            raise ValueError("SimBody needs a batch-of-one Gap: shapes (1,) and (1, 2)")
        self.blocked = False

    @classmethod
    def create(cls, maze: str, *, seed: int, index: int = 0, gap: bool = True) -> SimBody:
        """Robot `index` of `seed` in the named maze at a random free pose, gap on by default."""
        loaded = load_maze(maze)
        params = WorldParams()
        pose = free_pose(loaded, seed, index, params)
        return cls(loaded, pose, draw_gap(seed, index) if gap else None, params)

    @property
    def dt(self) -> float:
        return self.params.dt

    def step(self, left: float, right: float) -> None:
        """One dt with wheel commands in [-1, 1]; a move into a wall is refused."""
        motors = np.array([[left, right]], dtype=np.float64)
        moved = move(self.pose, motors, self.gap.motor_gain, self.params)
        self.blocked = bool(body_hits_wall(self.maze, moved, self.params)[0])
        if not self.blocked:
            self.pose = moved

    def whiskers(self) -> tuple[bool, ...]:
        bits = whisker_bits(self.maze, self.pose, self.params, self.gap.whisker_range)
        return tuple(bool(b) for b in bits[0])
