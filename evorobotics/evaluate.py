"""Evaluate controllers in the simulated maze (paper section 2.4): Eq 12 averaged over trials.

Every generation draws its trial conditions once, shared by every individual of the
generation, so an individual's fitness does not depend on which job (slice of the population)
it is evaluated in:

- trial start poses from rng(seed, generation, Purpose.START_POSES): uniform position and
  heading, rejected until the body is clear of walls and no whisker touches one;
- with the reality gap on, per trial t from rng(seed, generation, Purpose.REALITY_GAP, t): each
  whisker's trigger distance and each wheel's gain in the world's gap ranges (by default
  25-100 mm and 0.85-1.15 of the nominal gain, section 4); with the world's "step" gap model,
  every whisker's trigger distance of every step instead.

A run's validation set (`validate`) and exploration reports (`evorobotics.explore`) draw the
same way from streams of their own, so they never reuse a training pose.

Robots are independent of their batch-mates, so a batch can be cut into contiguous slices
simulated on threads (`threads=`; the kernel releases the GIL) with bit-identical results:
`colony evolve` uses every core this way, workers and the server's executor one thread each
(one of them per core already).
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache, lru_cache
from typing import TypeVar, get_args

import numpy as np

from evorobotics.errors import MazeError
from evorobotics.fitness import mean_fitness
from evorobotics.maze import Maze, is_shipped_or_generated, load_maze, maze_names
from evorobotics.seeds import Purpose, rng
from evorobotics.sim import DEFAULT_WORLD, Gap, SimResult, clear_of_walls, simulate
from schemas.run import Descriptor, RunConfig
from schemas.world import N_WHISKERS, World

_CANDIDATES = 64
_MAX_ROUNDS = 1000
_T = TypeVar("_T")


DESCRIPTORS: tuple[Descriptor, ...] = get_args(Descriptor)
"""("final_x", "final_y", "max_offset", "coverage"): the behaviour descriptors of an individual,
the columns of `Evaluation.descriptors`, each in [0, 1] and averaged over its trials: final x
and y over the maze's width and height, max offset (Eq 12) over the maze's diagonal, and the
fraction of the maze's free cells its centre visited."""


@dataclass(frozen=True)
class Evaluation:
    """Fitness (k,), Eq-12 components (k, trials, 4) and behaviour descriptors (k, 4) in
    DESCRIPTORS order, of k individuals."""

    fitness: np.ndarray
    components: np.ndarray
    descriptors: np.ndarray


def descriptors(maze: Maze, result: SimResult, k: int) -> np.ndarray:
    """(k, 4) DESCRIPTORS of k individuals from their trials' `result` (k * trials robots,
    individual-major): per-trial values normalised to the maze, then the mean over trials."""
    if result.cells is None:
        raise ValueError("the result has no visited-cell counts")
    free = int((~maze.solid).sum())
    per_trial = np.column_stack(
        [
            result.poses_final[:, 0] / maze.width,
            result.poses_final[:, 1] / maze.height,
            result.max_offset / math.hypot(maze.width, maze.height),
            result.cells / free,
        ]
    )
    return np.asarray(per_trial.reshape(k, -1, len(DESCRIPTORS)).mean(axis=1))


def start_poses(
    maze: Maze,
    seed: int,
    generation: int,
    trials: int,
    params: World = DEFAULT_WORLD,
    purpose: Purpose = Purpose.START_POSES,
) -> np.ndarray:
    """(trials, 3) random free poses: body clear of walls, every whisker untriggered (read-only).

    Candidates are drawn in rounds of 64 and accepted in draw order, so the result is a pure
    function of (maze, seed, generation, trials, params, purpose): training poses come from
    Purpose.START_POSES, validation and exploration poses from streams of their own. Every job
    of a generation asks for the same poses, so the last START_CACHE draws of this process are
    kept (keyed by the Maze object, as `load_maze` hands out one per spec); the array is a
    read-only view of the cached one, so no caller can change another's poses.
    """
    if trials < 0:
        raise ValueError(f"trials must be >= 0, got {trials}")
    return _cached_start_poses(maze, seed, generation, trials, params, purpose).view()


START_CACHE = 64
"""Entries of the start-pose and reality-gap caches: a few generations of a few runs."""


@lru_cache(maxsize=START_CACHE)
def _cached_start_poses(
    maze: Maze, seed: int, generation: int, trials: int, params: World, purpose: Purpose
) -> np.ndarray:
    poses = _draw_start_poses(maze, seed, generation, trials, params, purpose)
    poses.flags.writeable = False
    return poses


def _draw_start_poses(
    maze: Maze, seed: int, generation: int, trials: int, params: World, purpose: Purpose
) -> np.ndarray:
    """`start_poses` without the cache: the draws themselves."""
    return free_poses(maze, rng(seed, generation, purpose), trials, params)


def free_poses(maze: Maze, gen: np.random.Generator, trials: int, params: World) -> np.ndarray:
    """(trials, 3) uniform random poses from `gen` whose body is clear and no whisker touches a wall:
    candidates drawn 64 at a time (x, y, heading), accepted in draw order (a fresh array)."""
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


def draw_gap(
    seed: int,
    generation: int,
    trials: int,
    world: World = DEFAULT_WORLD,
    purpose: Purpose = Purpose.REALITY_GAP,
    steps: int | None = None,
) -> Gap:
    """Reality-gap draws of `trials` trials from `purpose`'s stream (read-only arrays).

    Trial t draws from rng(seed, generation, purpose, t) (`trial_gap`): whisker_range
    (trials, 5), each whisker's trigger distance, and motor_gain (trials, 2). With
    `world.gap_model == "step"` the stream goes on to draw every whisker's distance of every
    step, step by step, and whisker_range is (trials, steps, 5): `steps`, the trial length, is
    then required. The gains are the trial model's either way, and a shorter trial's draws are
    a longer one's first steps. Cached like `start_poses` (every job of a generation draws the
    same), except step-model draws over GAP_CACHE_STEPS robot-steps (a validation set, an
    exploration report: drawn once per use, 40 bytes a robot-step); read-only views.
    """
    if trials < 0:
        raise ValueError(f"trials must be >= 0, got {trials}")
    if world.gap_model == "trial":
        steps = 0  # not drawn: one cache entry whatever the trial length
    elif steps is None or steps < 0:
        raise ValueError(f"the 'step' gap model needs the trial length: steps >= 0, got {steps}")
    if trials * steps > GAP_CACHE_STEPS:
        return _draw_gap(seed, generation, trials, world, purpose, steps)
    cached = _cached_gap(seed, generation, trials, world, purpose, steps)
    return Gap(cached.whisker_range.view(), cached.motor_gain.view())


GAP_CACHE_STEPS = 20_000
"""Step-model gap draws of at most this many robot-steps (800 kB) are cached."""


def trial_gap(
    gen: np.random.Generator, world: World, steps: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """One trial's robot under the reality gap, from `gen`: each whisker's trigger distance
    (5,) uniform in `world.gap_whisker_range`, then each wheel's gain (2,), `world.motor_gain`
    times uniform 1 +- `world.gap_motor_gain`; with `steps` (the step model) every step's five
    distances after them, (steps, 5), in place of the trial's. A world with `gap_robots` (the
    colony gap) first draws which of them, then each value uniform within its uncertainty."""
    lo: np.ndarray | float
    hi: np.ndarray | float
    if world.gap_robots:
        robot = world.gap_robots[int(gen.integers(len(world.gap_robots)))]
        lo, hi = (np.array(b) for b in robot.whisker_bounds())
        ranges = gen.uniform(lo, hi)
        gains = gen.uniform(*(np.array(b) for b in robot.gain_bounds()))
    else:
        lo, hi = world.gap_whisker_range
        ranges = gen.uniform(lo, hi, N_WHISKERS)
        g = world.gap_motor_gain
        gains = np.array(world.motor_gain) * gen.uniform(1.0 - g, 1.0 + g, 2)
    if steps is not None:
        ranges = gen.uniform(lo, hi, (steps, N_WHISKERS))
    return ranges, gains


def _draw_gap(
    seed: int, generation: int, trials: int, world: World, purpose: Purpose, steps: int
) -> Gap:
    """`draw_gap` without the cache: the draws themselves, in read-only arrays."""
    per_step = world.gap_model == "step"
    ranges = np.empty((trials, steps, N_WHISKERS) if per_step else (trials, N_WHISKERS))
    gains = np.empty((trials, 2))
    for t in range(trials):
        gen = rng(seed, generation, purpose, t)
        ranges[t], gains[t] = trial_gap(gen, world, steps if per_step else None)
    ranges.flags.writeable = False
    gains.flags.writeable = False
    return Gap(ranges, gains)


_cached_gap = lru_cache(maxsize=START_CACHE)(_draw_gap)


def crossing_steps(maze: Maze, world: World = DEFAULT_WORLD) -> int:
    """The paper's trial length: a robot at full speed just crosses the maze, no time to return.

    "Run times were limited so that the best possible performance would result in travel from
    one side of the environment to the other without time for a return trip" (section 2.4):
    the longer side of the maze over one step's travel at full speed, rounded up.
    """
    return max(1, math.ceil(max(maze.width, maze.height) / world.step_length - 1e-9))


def trial_steps(config: RunConfig) -> int:
    """Steps of each training trial: `config.steps`, or `config.crossings` crossings of its
    maze (`crossing_steps`)."""
    if config.steps is not None:
        return config.steps
    return config.crossings * crossing_steps(load_maze(config.maze), config.world)


def check_config(config: RunConfig, *, files: bool = True) -> None:
    """Raise MazeError or ValueError naming the problem when the run's maze cannot be built or
    has no room for the robot (its generation 0's start poses), before the run starts: `colony
    evolve` and `POST /api/runs` both ask here. `files=False` refuses a maze read from a file
    (a server must not read its own files on a client's word)."""
    if not files and not is_shipped_or_generated(config.maze):
        raise MazeError(
            f"{config.maze!r} is not a shipped maze {maze_names()}, gen:SIZE:SEED or maze text"
        )
    start_poses(load_maze(config.maze), config.seed, 0, config.trials, config.world)
    trial_steps(config)
    config.training_world  # noqa: B018 - raises for a colony gap without its robots


def robot_steps(config: RunConfig, individuals: int) -> int:
    """Robot-steps of one generation of `individuals`: individuals x trials x trial steps."""
    return individuals * config.trials * trial_steps(config)


def full_speed_reach(world: World, steps: int, *, gap: bool = True) -> float:
    """How far `steps` steps at full speed take the fastest robot `world` allows (with `gap`,
    the fastest wheel gain its reality gap draws: the paper's, or a calibrated robot's of the
    colony gap), with room for rounding: the bound on every claimed distance."""
    gain = max(world.motor_gain)
    if gap:
        fastest = [max(robot.gain_bounds()[1]) for robot in world.gap_robots]
        gain = max([gain * (1.0 + world.gap_motor_gain), *fastest])
    return steps * world.step_length * gain * (1.0 + 1e-9) + 1e-9


def implausible(
    config: RunConfig, fitness: np.ndarray, components: np.ndarray, descriptors: np.ndarray
) -> str | None:
    """Why a claimed evaluation of n individuals, fitness (n,), components (n, trials, 4) and
    descriptors (n, 4), cannot come from `config`'s trials, or None: every component finite
    and within what a robot at full speed (the fastest wheel gain the gap allows) reaches in
    the trial's steps, stuck 0 or 1, each fitness Eq 12 of its components, and every
    descriptor in [0, 1] (DESCRIPTORS are fractions of the maze). A worker cannot forge a
    fitness or a descriptor beyond physics, only, at most, a plausible one (which spot-checks
    catch)."""
    n = fitness.shape[0]
    if (
        fitness.shape != (n,)
        or components.shape != (n, config.trials, 4)
        or descriptors.shape != (n, len(DESCRIPTORS))
    ):
        return (
            f"fitness {fitness.shape}, components {components.shape} and descriptors "
            f"{descriptors.shape} do not match"
        )
    if not (np.isfinite(fitness).all() and np.isfinite(components).all()):
        return "fitness and components must be finite"
    if not ((descriptors >= 0.0) & (descriptors <= 1.0)).all():  # NaN fails too
        return "a descriptor outside [0, 1]"
    maze = load_maze(config.maze)
    reach = full_speed_reach(config.world, trial_steps(config))
    offset = min(reach, math.hypot(maze.width, maze.height) * (1.0 + 1e-9))
    curve, net, far, stuck = (components[..., i] for i in range(4))
    if not ((curve >= 0) & (curve <= reach)).all():
        return f"a curve length outside [0, {reach:.6g}] m, the trial's reach at full speed"
    if not ((net >= 0) & (far >= 0) & (net <= offset) & (far <= offset)).all():
        return f"an offset outside [0, {offset:.6g}] m"
    if not ((stuck == 0.0) | (stuck == 1.0)).all():
        return "a stuck component other than 0 or 1"
    expected = mean_fitness(components, config.fitness)
    if not np.allclose(fitness, expected, rtol=1e-9, atol=1e-9):
        k = int(np.argmax(~np.isclose(fitness, expected, rtol=1e-9, atol=1e-9)))
        return f"fitness {fitness[k]!r} of individual {k} is not Eq 12 of its components"
    return None


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity): `colony evolve`'s default threads."""
    return len(os.sched_getaffinity(0))


def thread_slices(n: int, threads: int, most: int | None = None) -> list[tuple[int, int]]:
    """Contiguous [start, stop) slices covering 0..n in order, as even as possible: a multiple
    of `threads` of them (every thread gets as many), none longer than `most`, none empty
    unless n = 0 (one slice (0, 0))."""
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    if most is not None and most < 1:
        raise ValueError(f"most must be >= 1, got {most}")
    if n < 1:
        return [(0, 0)]
    least = 1 if most is None else -(-n // most)  # slices no longer than `most`
    count = min(n, threads * -(-least // threads))
    return list(itertools.pairwise(n * i // count for i in range(count + 1)))


@cache
def _pool(workers: int) -> ThreadPoolExecutor:
    """One pool per size for the process: its threads are started once, not per call."""
    return ThreadPoolExecutor(workers, thread_name_prefix="evaluate")


os.register_at_fork(after_in_child=_pool.cache_clear)  # a forked child has none of its threads


def map_slices(
    work: Callable[[int, int], _T], slices: list[tuple[int, int]], threads: int
) -> list[_T]:
    """`work(start, stop)` of every slice, in order, on up to `threads` threads: the caller
    takes the first slice and a process-wide pool the others (one thread: no pool at all)."""
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")

    def run(group: list[tuple[int, int]]) -> list[_T]:
        return [work(a, b) for a, b in group]

    if threads == 1 or len(slices) == 1:
        return run(slices)
    per_thread = -(-len(slices) // threads)
    groups = [slices[i : i + per_thread] for i in range(0, len(slices), per_thread)]
    pending = [_pool(threads - 1).submit(run, group) for group in groups[1:]]
    first = run(groups[0])
    return first + [item for future in pending for item in future.result()]


def _trials(
    config: RunConfig,
    genomes: np.ndarray,
    poses: np.ndarray,
    per_trial: Gap | None,
    steps: int,
) -> Evaluation:
    """Every (individual, trial) pair of k genomes in one batch; Eq 12 averaged over trials."""
    spec = config.network_spec
    g = np.asarray(genomes, dtype=np.float64)
    if g.ndim != 2 or g.shape[1] != spec.weight_count:
        raise ValueError(f"genomes must be (k, {spec.weight_count}), got {g.shape}")
    k, trials = g.shape[0], poses.shape[0]
    maze = load_maze(config.maze)
    result = simulate(
        spec,
        np.repeat(g, trials, axis=0),
        maze,
        np.tile(poses, (k, 1)),
        steps,
        params=config.world,
        gap=None if per_trial is None else per_trial.tile(k),
    )
    components = result.components.reshape(k, trials, 4)
    return Evaluation(
        mean_fitness(components, config.fitness), components, descriptors(maze, result, k)
    )


def evaluate(
    config: RunConfig, generation: int, genomes: np.ndarray, *, threads: int = 1
) -> Evaluation:
    """Eq 12 of k genomes (k, n_weights) on the generation's training trials, simulated in
    `threads` contiguous slices on as many threads (`thread_slices`): the same bits whatever
    the count."""
    maze = load_maze(config.maze)
    poses = start_poses(maze, config.seed, generation, config.trials, config.world)
    steps = trial_steps(config)
    gap = (
        draw_gap(config.seed, generation, config.trials, config.training_world, steps=steps)
        if config.trains_under_gap(generation)
        else None
    )
    g = np.asarray(genomes, dtype=np.float64)
    if g.ndim != 2:
        raise ValueError(f"genomes must be (k, {config.network_spec.weight_count}), got {g.shape}")
    parts = map_slices(
        lambda a, b: _trials(config, g[a:b], poses, gap, steps),
        thread_slices(len(g), threads),
        threads,
    )
    if len(parts) == 1:
        return parts[0]
    return Evaluation(
        *(
            np.concatenate([getattr(p, f) for p in parts])
            for f in ("fitness", "components", "descriptors")
        )
    )


def validation_set(config: RunConfig) -> tuple[np.ndarray, Gap | None]:
    """The run's validation trials: (poses, 3) start poses and, with the gap on, their draws.

    Poses from rng(seed, 0, Purpose.VALIDATION), gap draws from Purpose.VALIDATION_GAP in the
    run's `training_world`:
    streams no training trial draws from, so a champion is chosen on poses it was never
    trained on, the same ones for every candidate. Fresh writeable arrays.
    """
    v = config.validation
    maze = load_maze(config.maze)
    poses = start_poses(maze, config.seed, 0, v.poses, config.world, Purpose.VALIDATION).copy()
    if not config.gap:
        return poses, None
    drawn = draw_gap(
        config.seed, 0, v.poses, config.training_world, Purpose.VALIDATION_GAP, v.steps
    )
    return poses, Gap(drawn.whisker_range.copy(), drawn.motor_gain.copy())


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
    return simulate(
        spec, w, load_maze(config.maze), pose, steps, params=config.world, gap=gap, record=True
    )


PATH_STEPS = 200
"""Fig 6: the best controller drives longer than in training, to show its behaviour."""

PATH_TRIALS = 3


def unseen_paths(
    config: RunConfig, genome: np.ndarray, trials: int = PATH_TRIALS, steps: int = PATH_STEPS
) -> SimResult:
    """One genome's `trials` recorded trials of `steps` steps from start poses evolution never
    saw: `start_poses` of generation `config.generations`, one past the last trained, drawn
    for the default world as docs/evolve.md says (Fig 6's paths, `plots.paths_plot`); no
    reality gap."""
    maze = load_maze(config.maze)
    starts = start_poses(maze, config.seed, config.generations, trials)
    w = np.repeat(np.asarray(genome, dtype=np.float64).reshape(1, -1), trials, axis=0)
    return simulate(config.network_spec, w, maze, starts, steps, params=config.world, record=True)
