"""A robot's physics fitted from its own traces: each whisker's trigger range, each wheel's gain.

The paper measured its EvBots by hand (whiskers triggering at 25-100 mm, motors within 15 %);
the colony records, per control step, the pose the robot was sensed at (from an overhead
tracker, or an emulator's true pose, never odometry, which assumes the physics it would fit),
the five whisker bits read there and the wheel commands sent. Both fits replay the recorded
commands from the recorded poses under the simulator's own geometry and kinematics:

- wheel gains: a step's pose increment under `evorobotics.sim.move` is linear in the two
  gains (midpoint integration: the turn gives right - left, the advance along the mid heading
  left + right), so they are a least-squares fit over every step that moved. Steps whose move
  was refused (a wall: the pose did not change) carry no information and are left out.
- whisker ranges: at each recorded pose, the distance at which whisker k would first touch a
  wall (bisection of `whisker_bits` over the range, the simulator's exact ray test) is below
  the range exactly when the bit is 1. The range is the threshold that agrees with the most
  bits, at the middle of the widest such gap; its uncertainty is half that gap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evorobotics.errors import EvoError
from evorobotics.maze import Maze
from evorobotics.sim import whisker_bits
from schemas.world import N_WHISKERS, World

MAX_RANGE = 0.25
"""Metres: whisker distances are searched up to this (the gap's 100 mm and beyond)."""
MIN_SAMPLES = 100
"""Fewer steps than this fit nothing (10 s of robot time)."""
OUTLIER_FLOOR = 1e-9
"""Residuals (in wheel-command units) below this are never dropped as outliers."""
BISECTIONS = 40
"""Halvings of [0, MAX_RANGE]: well under a micrometre."""


class CalibrationError(EvoError):
    """The traces cannot calibrate the robot: too few, no poses, or a robot that never moved."""


@dataclass(frozen=True)
class Calibration:
    """Fitted physics, their uncertainties (same units) and how well they replay the traces."""

    whisker_range: tuple[float, ...]
    motor_gain: tuple[float, float]
    whisker_range_uncertainty: tuple[float, ...]
    motor_gain_uncertainty: tuple[float, float]
    samples: int
    moving_steps: int
    pose_residual_m: float
    """RMS distance between each recorded next pose and the one the fitted gains predict."""
    whisker_disagreements: tuple[int, ...]
    """Recorded bits per whisker that the fitted range would have read otherwise."""
    bounded: tuple[int, ...] = ()
    """Whiskers whose bit never changed: the traces give their range only as an interval (never
    a wall: below the nearest wall passed; always one: above the farthest), so their range is
    its middle and their uncertainty half of it."""

    def as_dict(self) -> dict[str, object]:
        """`colony robot calibrate --json`: the fit, its uncertainty and its residuals."""
        return {
            "whisker_range": list(self.whisker_range),
            "motor_gain": list(self.motor_gain),
            "uncertainty": {
                "whisker_range": list(self.whisker_range_uncertainty),
                "motor_gain": list(self.motor_gain_uncertainty),
            },
            "samples": self.samples,
            "residuals": {
                "moving_steps": self.moving_steps,
                "pose_rms_m": self.pose_residual_m,
                "whisker_disagreements": list(self.whisker_disagreements),
            },
            "bounded": list(self.bounded),
        }


def touch_distances(maze: Maze, poses: np.ndarray, world: World) -> np.ndarray:
    """(N, 5): the smallest range at which each whisker reads 1 at each pose (inf: none up to
    MAX_RANGE), by bisection of the simulator's own whisker test."""
    n = poses.shape[0]
    lo = np.zeros((n, N_WHISKERS))
    hi = np.full((n, N_WHISKERS), MAX_RANGE)
    far = whisker_bits(maze, poses, world, hi) == 0
    for _ in range(BISECTIONS):
        mid = (lo + hi) * 0.5
        on = whisker_bits(maze, poses, world, mid) == 1
        hi = np.where(on, mid, hi)
        lo = np.where(on, lo, mid)
    return np.where(far, np.inf, hi)


def _threshold(distance: np.ndarray, bits: np.ndarray) -> tuple[float, float, int]:
    """The range that reads the most bits right (bit 1 iff distance <= range): the middle of
    the widest gap among the best, and the bits it still reads wrong. Its uncertainty is half
    that gap, or, when some bits disagree with every range (a bit read a step off its pose),
    as far as any range reading at most twice as many bits wrong reaches: those bits could
    as well be the noise."""
    order = np.argsort(distance, kind="stable")
    d, b = distance[order], bits[order].astype(np.int64)
    # a threshold between d[i-1] and d[i] reads the first i as 1: wrong are the 0s among them
    # and the 1s after them
    zeros_before = np.concatenate([[0], np.cumsum(1 - b)])
    ones_after = np.concatenate([np.cumsum(b[::-1])[::-1], [0]])
    wrong = zeros_before + ones_after
    edges = np.minimum(np.concatenate([[0.0], d, [MAX_RANGE]]), MAX_RANGE)  # inf: no wall near
    gaps = edges[1:] - edges[:-1]
    best = np.flatnonzero(wrong == wrong.min())
    i = int(best[np.argmax(gaps[best])])
    middle = (edges[i] + edges[i + 1]) * 0.5
    near = np.flatnonzero(wrong <= 2 * wrong.min())
    reach = max(middle - edges[near].min(), edges[near + 1].max() - middle)
    return float(middle), float(reach), int(wrong[i])


def calibrate(
    maze: Maze,
    poses: np.ndarray,
    whiskers: np.ndarray,
    motors: np.ndarray,
    world: World,
    follows: np.ndarray | None = None,
) -> Calibration:
    """Fit from recorded steps: poses (N, 3) each sensed at, whiskers (N, 5) read there,
    motors (N, 2) sent then; `follows` (N - 1,) says where step t's move ends at pose t + 1
    (False between two agent starts or across a gap in the traces; default: everywhere).
    CalibrationError on too few steps or a robot that never moved. A whisker whose bit never
    changed is known only within an interval (`Calibration.bounded`)."""
    poses = np.asarray(poses, dtype=np.float64)
    whiskers = np.asarray(whiskers)
    motors = np.asarray(motors, dtype=np.float64)
    n = poses.shape[0]
    if poses.shape != (n, 3) or whiskers.shape != (n, N_WHISKERS) or motors.shape != (n, 2):
        raise CalibrationError(
            f"need poses (N, 3), whiskers (N, 5) and motors (N, 2), got {poses.shape}, "
            f"{whiskers.shape} and {motors.shape}"
        )
    linked = np.ones(max(n - 1, 0), dtype=bool) if follows is None else np.asarray(follows)
    if linked.shape != (max(n - 1, 0),):
        raise CalibrationError(f"follows must be (N - 1,) = ({n - 1},), got {linked.shape}")
    if n < MIN_SAMPLES:
        raise CalibrationError(f"{n} samples with poses: at least {MIN_SAMPLES} are needed")
    if not (np.isfinite(poses).all() and np.isfinite(motors).all()):
        raise CalibrationError("the traces hold non-finite poses or motor commands")
    gains, gain_err, moving, residual = _fit_gains(poses, motors, world, linked.astype(bool))
    distance = touch_distances(maze, poses, world)
    ranges, range_err, wrong = [], [], []
    for k in range(N_WHISKERS):  # one bit throughout: [0, nearest wall] or [farthest, MAX_RANGE]
        r, err, bad = _threshold(distance[:, k], whiskers[:, k])
        ranges.append(r)
        range_err.append(err)
        wrong.append(bad)
    return Calibration(
        whisker_range=tuple(ranges),
        motor_gain=gains,
        whisker_range_uncertainty=tuple(range_err),
        motor_gain_uncertainty=gain_err,
        samples=n,
        moving_steps=moving,
        pose_residual_m=residual,
        whisker_disagreements=tuple(wrong),
        bounded=tuple(k for k in range(N_WHISKERS) if len(np.unique(whiskers[:, k])) == 1),
    )


def _fit_gains(
    poses: np.ndarray, motors: np.ndarray, world: World, linked: np.ndarray
) -> tuple[tuple[float, float], tuple[float, float], int, float]:
    """Least-squares wheel gains, their standard errors, the moving steps used and the RMS
    pose residual (m) of the fit."""
    start, end, m = poses[:-1], poses[1:], motors[:-1]
    turn = np.angle(np.exp(1j * (end[:, 2] - start[:, 2])))  # wrapped to (-pi, pi]
    dxy = end[:, :2] - start[:, :2]
    moved = linked & ((np.hypot(dxy[:, 0], dxy[:, 1]) > 0) | (turn != 0))
    if moved.sum() < 2:
        raise CalibrationError("the robot never moved in the traces: no wheel gains to fit")
    mid = start[:, 2] + turn * 0.5
    advance = dxy[:, 0] * np.cos(mid) + dxy[:, 1] * np.sin(mid)
    scale = world.max_speed * world.dt
    total = 2.0 * advance / scale  # left x gain_l + right x gain_r
    diff = turn * world.wheel_base / scale  # right x gain_r - left x gain_l
    a = np.concatenate([np.column_stack([m[:, 0], m[:, 1]]), np.column_stack([-m[:, 0], m[:, 1]])])[
        np.concatenate([moved, moved])
    ]
    y = np.concatenate([total, diff])[np.concatenate([moved, moved])]
    fit, _, rank, _ = np.linalg.lstsq(a, y, rcond=None)
    if rank < 2:
        raise CalibrationError(
            "the traces never drove one of the wheels while the robot moved: its gain cannot "
            "be fitted"
        )
    # a real link is not lockstep: a command can take effect a step late, and such steps lie
    # far off the fit; they are dropped (beyond 4 median absolute residuals) and it is redone
    res = np.abs(a @ fit - y)
    keep = res <= max(4.0 * float(np.median(res)), OUTLIER_FLOOR)
    if keep.sum() >= 2 and not keep.all():
        a, y = a[keep], y[keep]
        fit, *_ = np.linalg.lstsq(a, y, rcond=None)
    if not (np.isfinite(fit).all() and (fit > 0).all()):
        raise CalibrationError(
            f"the fit gives wheel gains {fit.round(4).tolist()}, not positive: the traces "
            "do not follow the drive model (a wheel wired backwards, or poses of another robot?)"
        )
    dof = max(len(y) - 2, 1)
    sigma2 = float(np.sum((a @ fit - y) ** 2)) / dof
    cov = sigma2 * np.linalg.pinv(a.T @ a)
    err = np.sqrt(np.maximum(np.diag(cov), 0.0))
    predicted_v = (m[:, 0] * fit[0] + m[:, 1] * fit[1]) * 0.5 * world.max_speed
    predicted_w = (m[:, 1] * fit[1] - m[:, 0] * fit[0]) * world.max_speed / world.wheel_base
    pmid = start[:, 2] + predicted_w * world.dt * 0.5
    px = start[:, 0] + predicted_v * world.dt * np.cos(pmid)
    py = start[:, 1] + predicted_v * world.dt * np.sin(pmid)
    miss = np.hypot(px - end[:, 0], py - end[:, 1])[moved]
    return (
        (float(fit[0]), float(fit[1])),
        (float(err[0]), float(err[1])),
        int(moved.sum()),
        float(np.sqrt(np.mean(miss**2))),
    )
