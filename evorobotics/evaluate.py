"""Evaluate controllers in the simulated maze (paper section 2.4): Eq 12 averaged over trials.

Every generation draws its trial conditions once, shared by every individual of the
generation, so an individual's fitness does not depend on which job (slice of the population)
it is evaluated in:

- trial start poses from rng(seed, generation, Purpose.START_POSES): uniform position and
  heading, rejected until the body is clear of walls and no whisker touches one;
- with `reality_gap` on, per trial t from rng(seed, generation, Purpose.REALITY_GAP, t): one
  whisker trigger distance uniform in [25, 100] mm and two wheel gains uniform in [0.85, 1.15].
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from evorobotics.errors import MazeError
from evorobotics.fitness import mean_fitness
from evorobotics.maze import Maze, load_maze
from evorobotics.seeds import Purpose, rng
from evorobotics.sim import (
    DEFAULT_WORLD,
    Gap,
    SimResult,
    WorldParams,
    clear_of_walls,
    simulate,
)
from schemas.run import RunConfig

GAP_WHISKER_RANGE = (0.025, 0.100)
"""Real whiskers trigger anywhere between 25 and 100 mm from their base (section 4)."""
GAP_MOTOR_GAIN = 0.15
"""Real motors are calibrated to within 15 % of the simulated ones (section 4)."""

_CANDIDATES = 64
_MAX_ROUNDS = 1000


@dataclass(frozen=True)
class Evaluation:
    """Fitness (k,) and Eq-12 components (k, trials, 4) of k individuals."""

    fitness: np.ndarray
    components: np.ndarray


def start_poses(
    maze: Maze, seed: int, generation: int, trials: int, params: WorldParams = DEFAULT_WORLD
) -> np.ndarray:
    """(trials, 3) random free poses: body clear of walls, every whisker untriggered (read-only).

    Candidates are drawn in rounds of 64 and accepted in draw order, so the result is a pure
    function of (maze, seed, generation, trials, params). Every job of a generation asks for the
    same poses, so the last START_CACHE draws of this process are kept (keyed by the Maze
    object, as `load_maze` hands out one per spec); the array is a read-only view of the cached
    one, so no caller can change another's poses.
    """
    if trials < 0:
        raise ValueError(f"trials must be >= 0, got {trials}")
    return _cached_start_poses(maze, seed, generation, trials, params).view()


START_CACHE = 64
"""Entries of the start-pose and reality-gap caches: a few generations of a few runs."""


@lru_cache(maxsize=START_CACHE)
def _cached_start_poses(
    maze: Maze, seed: int, generation: int, trials: int, params: WorldParams
) -> np.ndarray:
    poses = _draw_start_poses(maze, seed, generation, trials, params)
    poses.flags.writeable = False
    return poses


def _draw_start_poses(
    maze: Maze, seed: int, generation: int, trials: int, params: WorldParams
) -> np.ndarray:
    """`start_poses` without the cache: the draws themselves."""
    gen = rng(seed, generation, Purpose.START_POSES)
    accepted: list[np.ndarray] = [np.empty((0, 3))]
    found = 0
    for _ in range(_MAX_ROUNDS):
        if found >= trials:
            break
        cand = np.column_stack(
            [
                gen.uniform(0.0, maze.width, _CANDIDATES),
                gen.uniform(0.0, maze.height, _CANDIDATES),
                gen.uniform(-np.pi, np.pi, _CANDIDATES),
            ]
        )
        free = clear_of_walls(maze, cand, params)
        accepted.append(cand[free])
        found += int(free.sum())
    if found < trials:
        raise MazeError(f"maze {maze.name!r} has no room for the robot: no free start pose")
    # a copy owns its data: once the cache clears its writeable flag, no view can set it again
    return np.concatenate(accepted)[:trials].copy()


def draw_gap(seed: int, generation: int, trials: int) -> Gap:
    """Per-trial reality-gap draws (trials,), (trials, 2) from Purpose.REALITY_GAP (read-only).

    Cached like `start_poses` (every job of a generation draws the same); read-only views.
    """
    if trials < 0:
        raise ValueError(f"trials must be >= 0, got {trials}")
    cached = _cached_gap(seed, generation, trials)
    return Gap(cached.whisker_range.view(), cached.motor_gain.view())


@lru_cache(maxsize=START_CACHE)
def _cached_gap(seed: int, generation: int, trials: int) -> Gap:
    ranges = np.empty(trials)
    gains = np.empty((trials, 2))
    for t in range(trials):
        gen = rng(seed, generation, Purpose.REALITY_GAP, t)
        ranges[t] = gen.uniform(*GAP_WHISKER_RANGE)
        gains[t] = gen.uniform(1.0 - GAP_MOTOR_GAIN, 1.0 + GAP_MOTOR_GAIN, 2)
    ranges.flags.writeable = False
    gains.flags.writeable = False
    return Gap(ranges, gains)


def evaluate(config: RunConfig, generation: int, genomes: np.ndarray) -> Evaluation:
    """Eq 12 of k genomes (k, n_weights), every (individual, trial) pair in one batch."""
    spec = config.network_spec
    g = np.asarray(genomes, dtype=np.float64)
    if g.ndim != 2 or g.shape[1] != spec.weight_count:
        raise ValueError(f"genomes must be (k, {spec.weight_count}), got {g.shape}")
    k, trials = g.shape[0], config.trials
    maze = load_maze(config.maze)
    poses = start_poses(maze, config.seed, generation, trials)
    gap = None
    if config.reality_gap:
        per_trial = draw_gap(config.seed, generation, trials)
        gap = Gap(np.tile(per_trial.whisker_range, k), np.tile(per_trial.motor_gain, (k, 1)))
    result = simulate(
        spec, np.repeat(g, trials, axis=0), maze, np.tile(poses, (k, 1)), config.steps, gap=gap
    )
    components = result.components.reshape(k, trials, 4)
    return Evaluation(mean_fitness(components, config.fitness), components)


def record_path(
    config: RunConfig,
    genome: np.ndarray,
    start_pose: np.ndarray,
    steps: int,
    gap: Gap | None = None,
) -> SimResult:
    """One individual's trial with poses, whisker bits and motor commands per step (batch 1)."""
    spec = config.network_spec
    w = np.asarray(genome, dtype=np.float64).reshape(1, -1)
    pose = np.asarray(start_pose, dtype=np.float64).reshape(1, 3)
    return simulate(spec, w, load_maze(config.maze), pose, steps, gap=gap, record=True)
