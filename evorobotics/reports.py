"""A controller's reports as jobs: trials simulated anywhere, in slices, assembled anywhere.

An exploration report (`evorobotics.explore`) and a robustness map (`evorobotics.robustness`)
are means over independent trials, each a pure function of (controller, world, maze, seed,
its index). A report's job simulates trials start:stop (`stage_scores`, its `Result.scores`);
the rows of all its jobs, in order, make the report (`assemble`) as `explore` or `robustness`
computes it in one process, bit for bit, however the trials were sliced and whoever simulated
them. `implausible` names what no row of a report's steps can be.

A report job's config is `schemas.wire.report_config`: the controller's network and world with
the report's maze and seed; its `ReportSpec` the poses, steps and reality gap. A ranking of
a run's candidates in a robot's world (`rank`, `evorobotics.evolution.rank_in_world`) is asked
the same way: its job scores candidates start:stop on the validation set of its config (a
`ranking_config`, no `ReportSpec`), and the rows of all its jobs make the ranking (`ranked` of
`Validated.from_scores`).
"""

from __future__ import annotations

import math

import numpy as np

from evorobotics.evaluate import full_speed_reach
from evorobotics.evolution import champion_scores, stage_robot_steps, validate
from evorobotics.explore import PAPER_TRIAL, Exploration, exploration, exploration_trials
from evorobotics.maze import load_maze
from evorobotics.robustness import RobustnessMap, map_trials, robustness_map
from schemas.run import RunConfig
from schemas.wire import ReportSpec, Stage

Report = Exploration | RobustnessMap
"""What a report's jobs assemble into."""


def stage_scores(
    config: RunConfig,
    stage: Stage,
    genomes: np.ndarray,
    start: int,
    stop: int,
    report: ReportSpec | None = None,
) -> np.ndarray:
    """A stage job's `Result.scores`: a champion's stage's (`champion_scores`), a ranking's
    (`rank`: candidates `genomes` on the validation set of `config`, a `ranking_config`), or,
    with `report`, trials start:stop of the report of the one genome."""
    if stage == "rank":
        return validate(config, genomes).scores()
    if report is None:
        return champion_scores(config, stage, genomes, start, stop)
    spec, weights, v = config.network_spec, genomes[0], report
    if stage == "explore":
        return exploration_trials(
            spec, weights, start, stop, poses=v.poses, steps=v.steps, maze=config.maze,
            seed=config.seed, reality_gap=v.reality_gap, world=config.world,
        )  # fmt: skip
    if stage == "robustness" and not v.reality_gap:
        return map_trials(
            spec, weights, start, stop, poses=v.poses, steps=v.steps, maze=config.maze,
            seed=config.seed, world=config.world,
        )  # fmt: skip
    raise ValueError(f"no report of stage {stage} with reality_gap {v.reality_gap}")


def stage_steps(config: RunConfig, stage: Stage, n: int, report: ReportSpec | None = None) -> int:
    """Robot-steps of a job of n rows (`stage_robot_steps`; a report's: n trials)."""
    return stage_robot_steps(config, stage, n) if report is None else n * report.steps


def assemble(config: RunConfig, stage: Stage, report: ReportSpec, rows: np.ndarray) -> Report:
    """The report from the rows of all its trials, in order."""
    if stage == "explore":
        steps, gap = report.steps, report.reality_gap
        return exploration(rows, steps, config.maze, config.seed, gap, config.fitness)
    return robustness_map(rows, report.poses, report.steps, config.maze, config.seed)


def implausible(
    config: RunConfig, stage: Stage, report: ReportSpec, rows: np.ndarray
) -> str | None:
    """Why rows of an exploration report (`stage` explore) cannot come from its trials, or
    None: a stuck step or a coverage beyond its steps, a curve length or an offset beyond the
    fastest robot's reach (or the maze's diagonal). Bounds that hold whatever the steps, and a
    map's rows, are checked as the result is decoded (`schemas.wire.Result`)."""
    if stage != "explore":
        return None
    steps, world = report.steps, config.world
    stuck, near, far, coverage, curve = (rows[:, i] for i in (0, 2, 3, 4, 5))
    if (stuck > steps).any():
        return f"a stuck step beyond the report's {steps} steps"
    if (coverage > steps + 1).any():
        return f"more cells covered than the {steps + 1} positions of a trial"
    maze = load_maze(config.maze)
    diagonal = math.hypot(maze.width, maze.height) * (1.0 + 1e-9)
    h = min(PAPER_TRIAL, steps)
    if (curve > full_speed_reach(world, h, gap=report.reality_gap)).any():
        return f"a curve length beyond the reach of {h} steps at full speed"
    if (near > min(full_speed_reach(world, h, gap=report.reality_gap), diagonal)).any() or (
        far > min(full_speed_reach(world, steps, gap=report.reality_gap), diagonal)
    ).any():
        return "an offset beyond the reach at full speed or the maze's diagonal"
    return None
