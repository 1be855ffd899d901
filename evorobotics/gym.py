"""The EvBot maze as a Gymnasium environment: `import evorobotics.gym` registers ENV_ID.

`EvBotMazeEnv` is one robot, `EvBotMazeVectorEnv` N robots stepped in one compiled call
(`sim.step_bodies`); both run on `_Batch`, so they agree step for step. A step is the
simulator's step with the controller taken out: the action is the two wheel commands, the
observation the five whisker bits sensed at the new pose (after `reset`, at the start pose),
exactly what `simulate` feeds its controller at the next step.

Reward: the increase of Eq 12's fitness over the step, k1 * (length of the accepted move) +
k2 * (change of net offset) + k3 * (change of max offset) - k4 on the step the robot becomes
stuck. It telescopes: the rewards of an episode sum to Eq 12 of the trial (to rounding).
An episode terminates when the robot is stuck (`World.stuck_after` blocked steps in a row) and
is truncated after the trial length, `steps`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Final, SupportsFloat

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.error import ResetNeeded
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from evorobotics.evaluate import crossing_steps, free_poses, trial_gap
from evorobotics.maze import load_maze
from evorobotics.sim import Bodies, body_hits_wall, sense_bodies, step_bodies
from schemas.run import FitnessWeights, RunConfig
from schemas.world import N_WHISKERS, World

ENV_ID: Final = "EvoColony/EvBotMaze-v0"


def _world(world: World | Mapping[str, Any] | None) -> World:
    return world if isinstance(world, World) else World.model_validate(dict(world or {}))


def _fitness(fitness: FitnessWeights | Mapping[str, Any] | None) -> FitnessWeights:
    if isinstance(fitness, FitnessWeights):
        return fitness
    return FitnessWeights.model_validate(dict(fitness or {}))


class _Batch:
    """N robots' episodes: bodies, Eq 12 terms, step counts and reality-gap draws.

    Row i draws its start poses and gap from its own generator, so a row's episodes do not
    depend on the other rows (the single env is a batch of one).
    """

    def __init__(
        self,
        n: int,
        maze: str,
        world: World | Mapping[str, Any] | None,
        steps: int | None,
        fitness: FitnessWeights | Mapping[str, Any] | None,
        reality_gap: bool,
    ) -> None:
        self.maze = load_maze(maze)
        self.world = _world(world)
        self.weights = _fitness(fitness)
        crossings = RunConfig.model_fields["crossings"].default
        self.steps = crossings * crossing_steps(self.maze, self.world) if steps is None else steps
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"steps must be an integer >= 1, got {steps!r}")
        self.reality_gap = bool(reality_gap)
        self.n = n
        self.bodies = Bodies(
            np.zeros((n, 3)),
            np.tile(np.array(self.world.motor_gain), (n, 1)),
            np.tile(np.array(self.world.whisker_ranges), (n, 1)),
        )
        self.starts = np.zeros((n, 3))
        self.net = np.zeros(n)
        self.max_off = np.zeros(n)
        self.curve = np.zeros(n)
        self.t = np.zeros(n, dtype=np.int64)
        self.rngs: list[np.random.Generator] = [np.random.default_rng() for _ in range(n)]
        self.started = False

    def place(self, rows: np.ndarray, poses: np.ndarray | None = None) -> None:
        """Start new episodes in `rows`: given poses (len(rows), 3) or drawn; gap drawn."""
        b = self.bodies
        for k, r in enumerate(rows):
            gen = self.rngs[r]
            b.poses[r] = free_poses(self.maze, gen, 1, self.world)[0] if poses is None else poses[k]
            if self.reality_gap:
                b.ranges[r], b.gains[r] = trial_gap(gen, self.world)
                if self._per_step:
                    b.ranges[r] = self._step_ranges(r)
        self.starts[rows] = b.poses[rows]
        for a in (self.net, self.max_off, self.curve, b.travelled, b.blocked, self.t):
            a[rows] = 0
        b.stuck[rows] = False
        sense_bodies(self.maze, self.world, b, rows)
        self.started = True

    @property
    def _per_step(self) -> bool:
        return self.reality_gap and self.world.gap_model == "step"

    def _step_ranges(self, r: int) -> np.ndarray:
        return self.rngs[r].uniform(*self.world.gap_whisker_range, N_WHISKERS)

    def step(
        self, rows: np.ndarray, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One step of `rows` on `actions` (N, 2): (rewards, terminated, truncated) of all N
        (meaningful in `rows`). Commands are taken as `network.motor_commands` gives them: NaN
        is 0 and values are clipped to [-1, 1]."""
        if not self.started:
            raise ResetNeeded("call reset() before step()")
        motors = np.clip(np.nan_to_num(np.asarray(actions, np.float64), nan=0.0), -1.0, 1.0)
        b = self.bodies
        if self._per_step:
            for r in rows:
                b.ranges[r] = self._step_ranges(int(r))
        was_stuck = b.stuck.copy()
        step_bodies(self.maze, self.world, b, rows, motors)
        self.t[rows] += 1
        self.curve[rows] += b.travelled[rows]
        off = b.poses[rows, :2] - self.starts[rows, :2]
        net = np.sqrt(off[:, 0] * off[:, 0] + off[:, 1] * off[:, 1])
        new_max = np.maximum(self.max_off[rows], net)
        became_stuck = b.stuck[rows] & ~was_stuck[rows]
        w = self.weights
        rewards = np.zeros(self.n)
        rewards[rows] = (
            w.k1 * b.travelled[rows]
            + w.k2 * (net - self.net[rows])
            + w.k3 * (new_max - self.max_off[rows])
            - w.k4 * became_stuck
        )
        self.net[rows] = net
        self.max_off[rows] = new_max
        return rewards, b.stuck.copy(), self.t >= self.steps

    def components(self) -> np.ndarray:
        """(N, 4) Eq 12 terms so far, in `fitness.COMPONENTS` order."""
        return np.column_stack(
            [self.curve, self.net, self.max_off, self.bodies.stuck.astype(np.float64)]
        )

    def observations(self) -> np.ndarray:
        return self.bodies.whiskers.astype(np.int8)


def _observation_space() -> spaces.MultiBinary:
    return spaces.MultiBinary(N_WHISKERS)


def _action_space() -> spaces.Box:
    return spaces.Box(-1.0, 1.0, (2,), np.float32)


def _checked_poses(batch: _Batch, value: object, n: int) -> np.ndarray:
    """The `pose` reset option as (n, 3): finite, body clear of walls."""
    try:
        poses = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        poses = np.empty(0)
    shapes = [(n, 3), (3,)] if n == 1 else [(n, 3)]
    if poses.shape not in shapes or not np.isfinite(poses).all():
        raise ValueError(f"options['pose'] must be {n} finite (x, y, heading) triple(s)")
    poses = poses.reshape(n, 3)
    if body_hits_wall(batch.maze, poses, batch.world).any():
        raise ValueError("options['pose'] puts the robot's body in a wall")
    return poses


class EvBotMazeEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """One EvBot in a maze: MultiBinary(5) whiskers (left to right), Box(-1, 1, (2,)) wheels.

    Arguments: `maze` (shipped name, `gen:SIZE:SEED`, a file or maze text), `world` (a World or
    a mapping of its fields), `steps` (trial length; default RunConfig's crossings x
    `crossing_steps`), `fitness` (Eq 12 weights, a FitnessWeights or mapping), `reality_gap`
    (per episode, and with the "step" gap model per step, draws as in section 4).
    `reset(options={"pose": (x, y, heading)})` starts from a given pose.
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 10}  # noqa: RUF012

    def __init__(
        self,
        maze: str = "paper",
        world: World | Mapping[str, Any] | None = None,
        steps: int | None = None,
        fitness: FitnessWeights | Mapping[str, Any] | None = None,
        reality_gap: bool = False,
        render_mode: str | None = None,
    ) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self._batch = _Batch(1, maze, world, steps, fitness, reality_gap)
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self._batch.world.dt)}
        self.observation_space = _observation_space()
        self.action_space = _action_space()
        self._rows = np.zeros(1, dtype=np.int64)

    @property
    def steps(self) -> int:
        """Trial length: an episode is truncated after this many steps."""
        return int(self._batch.steps)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._batch.rngs[0] = self.np_random
        pose = (options or {}).get("pose")
        poses = None if pose is None else _checked_poses(self._batch, pose, 1)
        self._batch.place(self._rows, poses)
        return self._batch.observations()[0], self._info()

    def step(
        self, action: np.ndarray
    ) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (2,):
            raise ValueError(f"action must be two wheel commands, shape (2,), got {a.shape}")
        rewards, terminated, truncated = self._batch.step(self._rows, a.reshape(1, 2))
        info = self._info()
        return (
            self._batch.observations()[0],
            float(rewards[0]),
            bool(terminated[0]),
            bool(truncated[0]),
            info,
        )

    def _info(self) -> dict[str, Any]:
        return {
            "pose": self._batch.bodies.poses[0].copy(),
            "components": self._batch.components()[0],
        }

    def render(self) -> np.ndarray | None:
        """rgb_array: walls dark, floor light, the robot's body red, (H, W, 3) uint8."""
        if self.render_mode != "rgb_array":
            return None
        maze = self._batch.maze
        rows, cols = maze.grid.shape
        px = max(2, math.ceil(240 / max(rows, cols)))
        image = np.where(np.repeat(np.repeat(maze.grid, px, 0), px, 1)[..., None], 60, 235)
        image = np.broadcast_to(image, (*image.shape[:2], 3)).astype(np.uint8)
        x, y, th = self._batch.bodies.poses[0]
        size = maze.cell_size / px  # metres per pixel; pixel row 0 is the north edge
        u = (np.arange(cols * px) + 0.5) * size - x
        v = (rows * px - np.arange(rows * px) - 0.5) * size - y
        du = u[None, :] * math.cos(th) + v[:, None] * math.sin(th)
        dv = v[:, None] * math.cos(th) - u[None, :] * math.sin(th)
        w = self._batch.world
        body = (np.abs(du) <= w.body_length / 2) & (np.abs(dv) <= w.body_width / 2)
        image[body] = (200, 30, 30)
        return image


class EvBotMazeVectorEnv(VectorEnv[np.ndarray, np.ndarray, np.ndarray]):
    """`num_envs` EvBots in one maze, stepped in one compiled call; next-step autoreset.

    Sub-env i behaves as an `EvBotMazeEnv` reset with seed + i (`reset(seed=seed)`), and after an
    episode ends, the next `step` resets it (its action ignored, reward 0, terminated and
    truncated False), as gymnasium's NEXT_STEP autoreset mode specifies. Info holds "pose"
    (N, 3) and "components" (N, 4) arrays, each with its all-True "_" mask.
    """

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.NEXT_STEP}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int,
        maze: str = "paper",
        world: World | Mapping[str, Any] | None = None,
        steps: int | None = None,
        fitness: FitnessWeights | Mapping[str, Any] | None = None,
        reality_gap: bool = False,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        self.num_envs = num_envs
        self._batch = _Batch(num_envs, maze, world, steps, fitness, reality_gap)
        self.single_observation_space = _observation_space()
        self.single_action_space = _action_space()
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._all = np.arange(num_envs, dtype=np.int64)
        self._autoreset = np.zeros(num_envs, dtype=np.bool_)

    @property
    def steps(self) -> int:
        """Trial length: an episode is truncated after this many steps."""
        return int(self._batch.steps)

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Every sub-env: seed i is `seed + i` (or `seed[i]`); options={"pose": (N, 3)}."""
        super().reset(seed=seed if isinstance(seed, int) else None)
        seeds: list[int | None]
        if seed is None:  # keep each sub-env's generator going
            seeds = [None] * self.num_envs
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed must be an int or {self.num_envs} seeds, got {len(seeds)}")
        for i, s in enumerate(seeds):
            if s is not None:
                self._batch.rngs[i] = seeding.np_random(s)[0]
        pose = (options or {}).get("pose")
        poses = None if pose is None else _checked_poses(self._batch, pose, self.num_envs)
        self._batch.place(self._all, poses)
        self._autoreset[:] = False
        return self._batch.observations(), self._info()

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (self.num_envs, 2):
            raise ValueError(f"actions must be ({self.num_envs}, 2) wheel commands, got {a.shape}")
        restart = self._autoreset
        rows = self._all[~restart]
        rewards, terminated, truncated = self._batch.step(rows, a)
        if restart.any():
            self._batch.place(self._all[restart])
            terminated[restart] = False
            truncated[restart] = False
        self._autoreset = terminated | truncated
        return self._batch.observations(), rewards, terminated, truncated, self._info()

    def _info(self) -> dict[str, Any]:
        mask = np.ones(self.num_envs, dtype=np.bool_)
        return {
            "pose": self._batch.bodies.poses.copy(),
            "_pose": mask,
            "components": self._batch.components(),
            "_components": mask.copy(),
        }


gymnasium.register(
    id=ENV_ID,
    entry_point="evorobotics.gym:EvBotMazeEnv",
    vector_entry_point="evorobotics.gym:EvBotMazeVectorEnv",
)
