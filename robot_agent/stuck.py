"""Is the robot stuck? Heuristics over whisker and motor history, no position sensing.

An EvBot knows only what it senses (five whisker bits) and what it commands (two wheels), so
the agent decides "stuck" from their history (docs/stuck-detection.md has the measured
precision and recall and the reasoning behind the defaults). Three signs, each configurable:

- contact held: some whisker has been on for `contact_steps` steps in a row while the wheels
  drive. A robot pressed against a wall keeps its whiskers bent; one that gets away loses them.
- pattern recurs: the same whisker pattern has started `recur_count` times within the last
  `recur_window` steps: the robot bumps the same wall over and over (the paper's "bump up
  against the same wall over and over again").
- spinning: for `spin_steps` steps in a row the wheels have turned the robot in place (their
  mean is small next to their difference) with no whisker touching: the paper's "spinning
  perpetually in one spot".

The detector is fed one step at a time by the agent loop (the same dt as the simulator) and
returns the sign it sees, or None; the agent asks for a new controller when it is not None.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from robot_agent.serial_protocol import WHISKERS


class StuckReason(StrEnum):
    """Which heuristic fired."""

    CONTACT_HELD = "contact-held"
    PATTERN_RECURS = "pattern-recurs"
    SPINNING = "spinning"


@dataclass(frozen=True, slots=True)
class StuckConfig:
    """Thresholds, in control steps (dt = 0.1 s) and wheel-command units."""

    contact_steps: int = 25
    """Steps of unbroken contact while driving (2.5 s)."""
    recur_window: int = 80
    """Steps over which contact onsets are counted (8 s)."""
    recur_count: int = 5
    """Onsets of one same pattern within the window."""
    spin_steps: int = 60
    """Steps of turning in place without contact (6 s: a full turn at moderate speed)."""
    spin_ratio: float = 0.25
    """In place: |left + right| / 2 <= spin_ratio * |left - right| / 2."""
    drive_min: float = 0.1
    """Wheels count as driving when the larger command magnitude reaches this."""

    def __post_init__(self) -> None:
        for name in ("contact_steps", "recur_window", "recur_count", "spin_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"StuckConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.spin_ratio < 1:
            raise ValueError(f"spin_ratio must be in [0, 1), got {self.spin_ratio}")
        if not 0 <= self.drive_min <= 1:
            raise ValueError(f"drive_min must be in [0, 1], got {self.drive_min}")


class StuckDetector:
    """Streaming detector: `update` once per control step, `reset` after a new controller."""

    def __init__(self, config: StuckConfig | None = None) -> None:
        self.config = config or StuckConfig()
        self._onsets: deque[tuple[int, int]] = deque()
        self.reset()

    def reset(self) -> None:
        """Forget the history (a new controller deserves a fresh start)."""
        self._step = 0
        self._contact_run = 0
        self._spin_run = 0
        self._previous = 0
        self._onsets.clear()

    def update(self, whiskers: Sequence[bool], motors: Sequence[float]) -> StuckReason | None:
        """Feed the step's sensed whiskers and commanded wheels; the sign seen, if any."""
        if len(whiskers) != WHISKERS or len(motors) != 2:
            raise ValueError(f"need {WHISKERS} whiskers and 2 motors")
        cfg = self.config
        left, right = float(motors[0]), float(motors[1])
        pattern = sum(1 << k for k, w in enumerate(whiskers) if w)
        driving = max(abs(left), abs(right)) >= cfg.drive_min
        self._step += 1

        self._contact_run = self._contact_run + 1 if pattern and driving else 0
        if pattern and pattern != self._previous:
            self._onsets.append((self._step, pattern))
        while self._onsets and self._onsets[0][0] <= self._step - cfg.recur_window:
            self._onsets.popleft()
        self._previous = pattern
        in_place = abs(left + right) <= cfg.spin_ratio * abs(left - right)
        self._spin_run = self._spin_run + 1 if driving and in_place and not pattern else 0

        if self._contact_run >= cfg.contact_steps:
            return StuckReason.CONTACT_HELD
        if pattern and sum(1 for _, p in self._onsets if p == pattern) >= cfg.recur_count:
            return StuckReason.PATTERN_RECURS
        if self._spin_run >= cfg.spin_steps:
            return StuckReason.SPINNING
        return None


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
