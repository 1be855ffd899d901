"""The simulator's EvBot as the emulator's physics: one robot, stepped one dt at a time.

Uses exactly `evorobotics.sim`'s sensing (`whisker_bits`), motion (`move`) and collision
(`body_hits_wall`) on a batch of one. One difference from a simulated trial, on purpose: a
blocked move leaves the pose unchanged but does not freeze the robot for good (the simulator's
`stuck` ends a trial; a real EvBot pressed against a wall can still back away), and the body
records `blocked` so traces carry the ground truth the stuck detector is measured against.

The start pose and reality gap of robot `index` are those `evorobotics.evaluate` gives trial
`index` of generation 0 (`start_poses`, `draw_gap`): a free pose with no whisker touching, each
whisker's trigger distance uniform in 25-100 mm, each wheel's gain within +/-15 % (paper section 4). With
the world's "step" gap model a virtual robot runs for as long as it is driven, so its whiskers'
distances cannot be drawn in advance: the body draws five anew on every step from
rng(seed, 0, Purpose.BODY_GAP, index).
"""

from __future__ import annotations

import numpy as np

from evorobotics.evaluate import draw_gap as draw_trial_gaps
from evorobotics.evaluate import start_poses
from evorobotics.maze import Maze, load_maze
from evorobotics.seeds import Purpose, rng
from evorobotics.sim import DEFAULT_WORLD, Gap, body_hits_wall, move, whisker_bits
from schemas.world import N_WHISKERS, World


def draw_gap(seed: int, index: int, world: World = DEFAULT_WORLD) -> Gap:
    """The per-trial reality gap of robot `index` under `seed` in `world`'s ranges, a
    batch-of-one Gap (the trial model's draws, whatever `world.gap_model`)."""
    gaps = draw_trial_gaps(seed, 0, index + 1, world.model_copy(update={"gap_model": "trial"}))
    return Gap(gaps.whisker_range[index:], gaps.motor_gain[index:])


class SimBody:
    """One simulated EvBot: pose, gap, and whether its last move was blocked by a wall.

    With `whisker_draws`, each whisker's trigger distance is drawn from it uniformly in
    `params.gap_whisker_range` anew on every step (the "step" gap model), in place of the
    gap's one distance.
    """

    def __init__(
        self,
        maze: Maze,
        pose: np.ndarray,
        gap: Gap | None = None,
        params: World | None = None,
        whisker_draws: np.random.Generator | None = None,
    ) -> None:
        self.params = params or World()
        self.maze = maze
        pose = np.asarray(pose, dtype=np.float64).reshape(1, 3)
        if body_hits_wall(maze, pose, self.params)[0]:
            raise ValueError(f"start pose {pose[0].tolist()} overlaps a wall")
        self.pose = pose
        self.gap = gap or Gap.nominal(1, self.params)
        if self.gap.whisker_range.shape not in ((1,), (1, N_WHISKERS)) or (
            self.gap.motor_gain.shape != (1, 2)
        ):
            raise ValueError("SimBody needs a batch-of-one Gap: shapes (1, 5) and (1, 2)")
        self.blocked = False
        self._whisker_draws = whisker_draws
        self.whisker_range = self._next_ranges()
        """The trigger distances of this step: (1,) one for all whiskers, or (1, 5)."""

    @classmethod
    def create(
        cls,
        maze: str,
        *,
        seed: int,
        index: int = 0,
        gap: bool = True,
        world: World = DEFAULT_WORLD,
    ) -> SimBody:
        """Robot `index` of `seed` in the named maze at a random free pose, gap on by default.

        `world` is the run's (its config.json or champion document carry it), so a virtual
        robot has the body, whiskers, speed and gap model the controller was evolved with.
        """
        loaded = load_maze(maze)
        pose = start_poses(loaded, seed, 0, index + 1, world)[index]
        if not gap:
            return cls(loaded, pose, None, world)
        draws = rng(seed, 0, Purpose.BODY_GAP, index) if world.gap_model == "step" else None
        return cls(loaded, pose, draw_gap(seed, index, world), world, draws)

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
        self.whisker_range = self._next_ranges()

    def position(self) -> tuple[float, float, float]:
        """The pose now: x, y (metres) and heading (radians), as the simulator holds them."""
        x, y, theta = self.pose[0]
        return float(x), float(y), float(theta)

    def whiskers(self) -> tuple[bool, ...]:
        bits = whisker_bits(self.maze, self.pose, self.params, self.whisker_range)
        return tuple(bool(b) for b in bits[0])

    def _next_ranges(self) -> np.ndarray:
        if self._whisker_draws is None:
            return self.gap.whisker_range
        return self._whisker_draws.uniform(*self.params.gap_whisker_range, (1, N_WHISKERS))
