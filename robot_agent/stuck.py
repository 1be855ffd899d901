"""Is the robot stuck? Heuristics over whisker and motor history, no position sensing.

An EvBot knows only what it senses (five whisker bits) and what it commands (two wheels), so
the agent decides "stuck" from their history (docs/stuck-detection.md has the measured
precision and recall and the reasoning behind the defaults). Two signs, each configurable,
and a third where an overhead tracker tells the robot where it is:

- contact held: some whisker has been on for `contact_steps` steps in a row while the wheels
  drive. A robot pressed against a wall keeps its whiskers bent; one that gets away loses them.
- going nowhere: dead reckoning of the commanded wheel speeds with the simulator's nominal
  kinematics (`World`) keeps the robot within `odometry_radius` of where it was
  `odometry_window` steps ago: spinning or circling in place (the paper's "spinning
  perpetually in one spot"), rocking, or idling. Commands are not motion (+/-15 % motors,
  slipping), but over a few seconds the estimate tells a tight loop from a journey.
- tracked still: the tracker's poses of the last `tracker_window` steps stayed within
  `tracker_radius` of the first. It sees what whiskers and commands cannot (a body corner
  pinned on a wall, every whisker clear, the wheels still driving forward), and while it has a
  whole window of poses it replaces going nowhere, which only estimates the same thing.

The detector is fed one step at a time by the agent loop (the same dt as the simulator) and
returns the sign it sees, or None; the agent asks for a new controller when it is not None.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from robot_agent.serial_protocol import WHISKERS
from schemas.world import World


class StuckReason(StrEnum):
    """Which heuristic fired."""

    CONTACT_HELD = "contact-held"
    GOING_NOWHERE = "going-nowhere"
    TRACKED_STILL = "tracked-still"


@dataclass(frozen=True, slots=True)
class StuckConfig:
    """Thresholds, in control steps (dt = 0.1 s) and wheel-command units."""

    contact_steps: int = 25
    """Steps of unbroken contact while driving (2.5 s)."""
    odometry_window: int = 50
    """Steps of dead reckoning looked back over (5 s)."""
    odometry_radius: float = 0.08
    """Metres: estimated path never left this disc around its start (half a body length)."""
    drive_min: float = 0.1
    """Wheels count as driving (for contact held) when the larger command reaches this."""
    tracker_window: int = 40
    """Steps of tracked poses looked back over (4 s)."""
    tracker_radius: float = 0.1
    """Metres: the tracked robot never left this disc around where the window began."""

    def __post_init__(self) -> None:
        if not self.tracker_radius > 0:
            raise ValueError(f"tracker_radius must be > 0, got {self.tracker_radius}")
        for name in ("contact_steps", "odometry_window", "tracker_window"):
            if getattr(self, name) < 1:
                raise ValueError(f"StuckConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not self.odometry_radius > 0:
            raise ValueError(f"odometry_radius must be > 0, got {self.odometry_radius}")
        if not 0 <= self.drive_min <= 1:
            raise ValueError(f"drive_min must be in [0, 1], got {self.drive_min}")


class StuckDetector:
    """Streaming detector: `update` once per control step, `reset` after a new controller."""

    def __init__(self, config: StuckConfig | None = None, world: World | None = None) -> None:
        self.config = config or StuckConfig()
        self.world = world or World()
        self._track: deque[tuple[float, float]] = deque(maxlen=self.config.odometry_window + 1)
        self._tracked: deque[tuple[float, float]] = deque(maxlen=self.config.tracker_window + 1)
        self.reset()

    def reset(self) -> None:
        """Forget the history (a new controller deserves a fresh start)."""
        self._contact_run = 0
        self._pose = (0.0, 0.0, 0.0)
        self._track.clear()
        self._track.append((0.0, 0.0))
        self._tracked.clear()

    def update(
        self,
        whiskers: Sequence[bool],
        motors: Sequence[float],
        pose: Sequence[float] | None = None,
    ) -> StuckReason | None:
        """Feed the step's sensed whiskers and commanded wheels, and the tracker's pose of the
        robot if one is fresh (None breaks the tracked window); the sign seen, if any."""
        if len(whiskers) != WHISKERS or len(motors) != 2:
            raise ValueError(f"need {WHISKERS} whiskers and 2 motors")
        cfg = self.config
        left, right = float(motors[0]), float(motors[1])
        driving = max(abs(left), abs(right)) >= cfg.drive_min
        self._contact_run = self._contact_run + 1 if any(whiskers) and driving else 0
        self._dead_reckon(left, right)

        if pose is None:
            self._tracked.clear()
        else:
            self._tracked.append((float(pose[0]), float(pose[1])))

        if self._contact_run >= cfg.contact_steps:
            return StuckReason.CONTACT_HELD
        if len(self._tracked) == self._tracked.maxlen:
            x0, y0 = self._tracked[0]
            r2 = cfg.tracker_radius**2
            if all((x - x0) ** 2 + (y - y0) ** 2 < r2 for x, y in self._tracked):
                return StuckReason.TRACKED_STILL
        elif len(self._track) == self._track.maxlen:
            x0, y0 = self._track[0]
            r2 = cfg.odometry_radius**2
            if all((x - x0) ** 2 + (y - y0) ** 2 < r2 for x, y in self._track):
                return StuckReason.GOING_NOWHERE
        return None

    def _dead_reckon(self, left: float, right: float) -> None:
        """The commanded move under nominal kinematics (as `evorobotics.sim.move`)."""
        p = self.world
        left, right = max(-1.0, min(1.0, left)), max(-1.0, min(1.0, right))
        v = (left + right) * 0.5 * p.max_speed
        w = (right - left) * p.max_speed / p.wheel_base
        x, y, th = self._pose
        mid = th + w * p.dt * 0.5
        x, y = x + v * p.dt * math.cos(mid), y + v * p.dt * math.sin(mid)
        self._pose = (x, y, th + w * p.dt)
        self._track.append((x, y))


def detect(
    whiskers: np.ndarray, motors: np.ndarray, config: StuckConfig | None = None
) -> list[StuckReason | None]:
    """Run a fresh detector over a whole trace: whiskers (T, 5), motors (T, 2)."""
    w = np.asarray(whiskers)
    m = np.asarray(motors, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != WHISKERS or m.shape != (w.shape[0], 2):
        raise ValueError(
            f"need whiskers (T, {WHISKERS}) and motors (T, 2), got {w.shape}, {m.shape}"
        )
    detector = StuckDetector(config)
    return [detector.update(tuple(bool(b) for b in w[t]), m[t]) for t in range(w.shape[0])]
