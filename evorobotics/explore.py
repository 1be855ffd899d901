"""Does a controller explore? Its behaviour over long horizons from unseen start poses.

The paper's claim is a robot that wanders a maze "indefinitely without getting stuck". One
report runs a controller from `poses` start poses (drawn from Purpose.EXPLORATION, a stream no
training or validation trial uses) for `steps` steps each and measures, per trial:

- stuck by step h: its body was blocked `world.stuck_after` times in a row by step h;
- confined: before any sticking, 100 consecutive steps (CONFINED_STEPS) with every position in
  a box of at most 0.3 m diagonal (CONFINED_DIAGONAL): spinning on the spot, or bumping the same
  wall again and again;
- roaming: neither stuck nor confined over the whole horizon;
- max offset by step h: the largest distance from the start position so far;
- coverage: distinct 0.1 m grid cells (COVERAGE_CELL) its centre visited;
- Eq 12 fitness of its first 40 steps (the paper's trial), with the run's weights.

Measured by the simulation kernel as the robots move (`watch`, `sim.simulate_watched`): no
path is recorded, so a report runs at the kernel's speed, on as many threads as asked.
`trials` computes the same rows from recorded paths (`simulate(record=True)`), the definition
the kernel's figures are tested against bit for bit. Deterministic in (controller, world, maze,
seed), whatever the threads.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numba import njit

from evorobotics.evaluate import draw_gap, map_slices, start_poses, thread_slices
from evorobotics.fitness import fitness
from evorobotics.maze import Maze, load_maze
from evorobotics.seeds import Purpose
from evorobotics.sim import Gap, SimResult, Watched, simulate_watched
from schemas.network import NetworkSpec
from schemas.run import FitnessWeights
from schemas.wire import REPORT_ROBOT_STEPS
from schemas.world import World

CONFINED_STEPS = 100
"""A confinement lasts this many consecutive steps (10 s of robot time)."""
CONFINED_DIAGONAL = 0.3
"""... inside a box of at most this diagonal (m): under two body lengths."""
COVERAGE_CELL = 0.1
"""Coverage counts distinct squares of this side (m): one maze cell."""
PAPER_TRIAL = 40
"""The paper's training trial: 40 steps (section 4)."""
HORIZONS = (40, 200)
"""Stuck fractions and offsets are also reported at these steps (when within the horizon)."""
MAX_ROBOT_STEPS = REPORT_ROBOT_STEPS
"""Upper bound on poses x steps of one report, so no request can exhaust memory or a worker's
time: nothing is recorded, but the per-step gap model draws 40 bytes a robot-step."""


@dataclass(frozen=True)
class Exploration:
    """One controller's exploration report (fractions of trials, metres, cells)."""

    poses: int
    steps: int
    maze: str
    seed: int
    reality_gap: bool
    stuck: dict[int, float]
    """step h -> fraction of trials stuck by step h (for 40, 200 and `steps`)."""
    confined: float
    roaming: float
    max_offset: dict[int, float]
    """step h -> mean max offset by step h, m (for 40 and `steps`)."""
    coverage: float
    """Mean distinct 0.1 m cells visited per trial."""
    fitness_40: float
    """Mean Eq 12 fitness over the first 40 steps of each trial."""

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: integer keys become strings."""
        out = asdict(self)
        out["stuck"] = {str(k): v for k, v in self.stuck.items()}
        out["max_offset"] = {str(k): v for k, v in self.max_offset.items()}
        return out


@njit(cache=True, nogil=True)
def _confined_rows(poses: np.ndarray, last: np.ndarray, span: int, diagonal: float) -> np.ndarray:
    """`confined`'s loop: per trial, the windows' extents from prefix and suffix extremes
    within blocks of `span` positions (van Herk-Gil-Werman: O(n) whatever the width), stopping
    at the first window that fits. Windows must end at or before position last[r]."""
    b, n = poses.shape[0], poses.shape[1]
    out = np.zeros(b, dtype=np.bool_)
    # [axis, position]: max and min from the block's start (head) and to its end (tail)
    head_hi, head_lo = np.empty((2, n)), np.empty((2, n))
    tail_hi, tail_lo = np.empty((2, n)), np.empty((2, n))
    for r in range(b):
        count = min(last[r] - span + 2, n - span + 1)
        if count <= 0:
            continue
        m = count + span - 1
        for a in range(2):
            for i in range(m):
                v = poses[r, i, a]
                if i % span == 0:
                    head_hi[a, i] = head_lo[a, i] = v
                else:
                    head_hi[a, i] = max(head_hi[a, i - 1], v)
                    head_lo[a, i] = min(head_lo[a, i - 1], v)
            for i in range(m - 1, -1, -1):
                v = poses[r, i, a]
                if i == m - 1 or (i + 1) % span == 0:
                    tail_hi[a, i] = tail_lo[a, i] = v
                else:
                    tail_hi[a, i] = max(tail_hi[a, i + 1], v)
                    tail_lo[a, i] = min(tail_lo[a, i + 1], v)
        for i in range(count):
            j = i + span - 1
            dx = max(tail_hi[0, i], head_hi[0, j]) - min(tail_lo[0, i], head_lo[0, j])
            dy = max(tail_hi[1, i], head_hi[1, j]) - min(tail_lo[1, i], head_lo[1, j])
            if math.hypot(dx, dy) <= diagonal:
                out[r] = True
                break
    return out


def confined(poses: np.ndarray, stuck_step: np.ndarray) -> np.ndarray:
    """(B,) bool: a window of CONFINED_STEPS steps inside a CONFINED_DIAGONAL box before sticking.

    `poses` (B, steps+1, 3) as `simulate(record=True)` gives them; a window of w steps spans
    w + 1 positions. Windows that reach past the step a robot stuck on do not count: being
    stuck is reported on its own. Compiled: validation scores 4,000 trials of 1,001 positions.
    """
    n = poses.shape[1]
    # a window ending at position i + CONFINED_STEPS counts if that step came before the robot
    # stuck (never stuck: every window counts)
    last = np.where(stuck_step >= 0, stuck_step - 1, n - 1).astype(np.int64)
    return np.asarray(
        _confined_rows(
            np.asarray(poses, dtype=np.float64), last, CONFINED_STEPS + 1, CONFINED_DIAGONAL
        )
    )


TRIAL_COLUMNS = ("stuck_step", "confined", "offset_40", "offset", "coverage", "curve_40", "net_40")
"""Columns of `trials`' rows, one trial each: the step it stuck on (-1: never), confined (0 or
1), its largest offset by step min(40, H) and by H (m), the cells it covered, and the curve
length and net offset of its first min(40, H) steps (Eq 12's terms of the paper's trial)."""


def watch(
    spec: NetworkSpec,
    weights: np.ndarray,
    maze: Maze,
    starts: np.ndarray,
    steps: int,
    world: World,
    gap: Gap | None = None,
) -> Watched:
    """Trials of `weights` (B, n_weights) from `starts` (B, 3), with this module's confinement,
    coverage and horizon (`sim.simulate_watched`): the one entry of every long-trial measure
    (reports, validation, the held-out test, robustness maps)."""
    return simulate_watched(
        spec,
        weights,
        maze,
        starts,
        steps,
        params=world,
        gap=gap,
        window=CONFINED_STEPS,
        diagonal=CONFINED_DIAGONAL,
        cell=COVERAGE_CELL,
        horizon=min(PAPER_TRIAL, steps),
    )


def watched_trials(watched: Watched) -> np.ndarray:
    """(B, TRIAL_COLUMNS) float64 of watched trials (`watch`): `trials` of the same trials
    recorded, bit for bit (the first moves summed by numpy, as there)."""
    return np.stack(
        [
            watched.stuck_step.astype(np.float64),
            watched.confined.astype(np.float64),
            watched.horizon_offset,
            watched.farthest,
            watched.coverage.astype(np.float64),
            watched.moves.sum(axis=1),
            watched.horizon_net,
        ],
        axis=1,
    )


def trials(result: SimResult, steps: int) -> np.ndarray:
    """(B, TRIAL_COLUMNS) float64 of one recorded batch of trials: every row depends on its
    own trial alone, so rows of any slices of the poses concatenate to the whole batch's."""
    if result.poses is None:
        raise ValueError("report needs a recorded simulation (record=True)")
    poses = result.poses
    start = poses[:, :1, :2]
    offsets = np.hypot(*(poses[:, :, :2] - start).transpose(2, 0, 1))
    h = min(PAPER_TRIAL, steps)
    cells = np.floor(poses[:, :, :2] / COVERAGE_CELL).astype(np.int64)
    keys = cells[:, :, 0] * 1_000_003 + cells[:, :, 1]
    moves = np.hypot(*np.diff(poses[:, : h + 1, :2], axis=1).transpose(2, 0, 1))
    return np.stack(
        [
            result.stuck_step.astype(np.float64),
            confined(poses, result.stuck_step).astype(np.float64),
            offsets[:, : h + 1].max(axis=1),
            offsets.max(axis=1),
            np.array([len(np.unique(row)) for row in keys], dtype=np.float64),
            moves.sum(axis=1),
            offsets[:, h],
        ],
        axis=1,
    )


def measures(rows: np.ndarray, weights: FitnessWeights, steps: int) -> dict[str, Any]:
    """The report's measures (see the module docstring) from the rows of all its trials
    (`trials`), in pose order."""
    if rows.ndim != 2 or rows.shape[1] != len(TRIAL_COLUMNS) or not len(rows):
        raise ValueError(f"rows {rows.shape} are not trials of {len(TRIAL_COLUMNS)} columns")
    stuck_step, near, far, coverage, curve, net = (
        np.ascontiguousarray(rows[:, i]) for i in (0, 2, 3, 4, 5, 6)
    )
    is_confined = rows[:, 1] == 1.0
    stuck = {
        h: float(np.mean((stuck_step >= 0) & (stuck_step <= h)))
        for h in (*HORIZONS, steps)
        if h <= steps
    }
    h = min(PAPER_TRIAL, steps)
    stuck_h = ((stuck_step >= 0) & (stuck_step <= h)).astype(np.float64)
    return {
        "stuck": stuck,
        "confined": float(np.mean(is_confined)),
        "roaming": float(np.mean(~is_confined & (stuck_step < 0))),
        "max_offset": {
            h: float(np.mean(far if h == steps else near))
            for h in (PAPER_TRIAL, steps)
            if h <= steps
        },
        "coverage": float(np.mean(coverage)),
        "fitness_40": float(
            np.mean(fitness(np.stack([curve, net, near, stuck_h], axis=-1), weights))
        ),
    }


def report(result: SimResult, weights: FitnessWeights, steps: int) -> dict[str, Any]:
    """The measures of one recorded batch of trials (see the module docstring)."""
    return measures(trials(result, steps), weights, steps)


def exploration_trials(
    spec: NetworkSpec,
    weights: np.ndarray,
    start: int,
    stop: int,
    *,
    poses: int,
    steps: int,
    maze: str,
    seed: int,
    reality_gap: bool,
    world: World,
    threads: int = 1,
) -> np.ndarray:
    """`trials` rows of poses start:stop of `explore`'s report, in slices on `threads`
    threads: a job of a report sliced among workers (`evorobotics.reports`); every slice's
    rows are the whole report's."""
    if not 0 <= start < stop <= poses:
        raise ValueError(f"poses {start}:{stop} outside the report's {poses}")
    check_size(poses, steps)
    loaded = load_maze(maze)
    starts = start_poses(loaded, seed, 0, poses, world, Purpose.EXPLORATION)
    drawn = draw_gap(seed, 0, poses, world, Purpose.EXPLORATION_GAP, steps) if reality_gap else None
    w = np.asarray(weights, dtype=np.float64).reshape(1, -1)

    def rows(a: int, b: int) -> np.ndarray:
        gap = None if drawn is None else Gap(drawn.whisker_range[a:b], drawn.motor_gain[a:b])
        trials = watch(spec, np.repeat(w, b - a, axis=0), loaded, starts[a:b], steps, world, gap)
        return watched_trials(trials)

    slices = [(start + a, start + b) for a, b in thread_slices(stop - start, threads)]
    return np.concatenate(map_slices(rows, slices, threads))


def check_size(poses: int, steps: int) -> None:
    """ValueError unless 1 <= poses, steps and poses x steps <= MAX_ROBOT_STEPS."""
    if poses < 1 or steps < 1:
        raise ValueError(f"poses and steps must be >= 1, got {poses} and {steps}")
    if poses * steps > MAX_ROBOT_STEPS:
        raise ValueError(
            f"poses x steps = {poses * steps} exceeds the limit of {MAX_ROBOT_STEPS} robot steps"
        )


def explore(
    spec: NetworkSpec,
    weights: np.ndarray,
    *,
    poses: int = 1000,
    steps: int = 1000,
    maze: str = "paper",
    seed: int = 0,
    reality_gap: bool = False,
    world: World | None = None,
    fitness_weights: FitnessWeights | None = None,
    threads: int = 1,
) -> Exploration:
    """The exploration report of one controller (see the module docstring), simulated on
    `threads` threads (the same figures whatever the count)."""
    check_size(poses, steps)
    rows = exploration_trials(
        spec,
        weights,
        0,
        poses,
        poses=poses,
        steps=steps,
        maze=maze,
        seed=seed,
        reality_gap=reality_gap,
        world=world or World(),
        threads=threads,
    )
    return exploration(rows, steps, maze, seed, reality_gap, fitness_weights)


def exploration(
    rows: np.ndarray,
    steps: int,
    maze: str,
    seed: int,
    reality_gap: bool,
    fitness_weights: FitnessWeights | None = None,
) -> Exploration:
    """The report from the rows of all its trials (`exploration_trials` of every pose, in
    order, wherever they were simulated): `explore`'s, bit for bit."""
    measured = measures(rows, fitness_weights or FitnessWeights(), steps)
    return Exploration(len(rows), steps, load_maze(maze).name, seed, reality_gap, **measured)
