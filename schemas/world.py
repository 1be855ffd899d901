"""The simulated world a run evolves in: robot kinematics, body, whiskers, stuck rule, gap.

Part of every run config (`RunConfig.world`), so it travels with the run to workers, is written
into config.json and into the champion's controller document. Defaults are the EvBot of the
paper (section 2.2 and 4); lengths in metres, times in seconds, angles in degrees.
"""

from __future__ import annotations

import json
import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

N_WHISKERS = 5
"""The EvBot's five binary whiskers: the controller's five inputs."""
MAX_GAP_ROBOTS = 256
"""Calibrated robots a world's colony gap may hold (a config stays small)."""


class GapRobot(BaseModel):
    """One calibrated robot of a colony (`colony robot calibrate`): under `reality_gap:
    "colony"` a trial's robot has each whisker's range and each wheel's gain drawn uniformly
    within value +- uncertainty."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    robot: str = Field("", max_length=64, description="whose calibration (for the record)")
    whisker_range: tuple[float, float, float, float, float] = Field(
        description="each whisker's fitted trigger distance, left to right, m"
    )
    whisker_uncertainty: tuple[float, float, float, float, float] = Field(
        description="half-width of each whisker's interval, m"
    )
    motor_gain: tuple[float, float] = Field(description="the wheels' fitted gains [left, right]")
    motor_gain_uncertainty: tuple[float, float] = Field(description="half-width of each gain's")

    @model_validator(mode="after")
    def _check(self) -> GapRobot:
        if not all(0.0 <= r <= 1.0 for r in self.whisker_range):
            raise ValueError(f"whisker_range must be within 0-1 m, got {self.whisker_range}")
        if not all(0.0 < g <= 10.0 for g in self.motor_gain):
            raise ValueError(f"motor_gain must be within (0, 10], got {self.motor_gain}")
        spreads = (*self.whisker_uncertainty, *self.motor_gain_uncertainty)
        if not all(0.0 <= u <= 1.0 for u in spreads):
            raise ValueError(f"uncertainties must be within 0-1, got {spreads}")
        return self

    def whisker_bounds(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Each whisker's interval, clipped to 0-1 m."""
        pairs = list(zip(self.whisker_range, self.whisker_uncertainty, strict=True))
        return tuple(max(0.0, r - u) for r, u in pairs), tuple(min(1.0, r + u) for r, u in pairs)

    def gain_bounds(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Each wheel's interval, kept above 0 (a wheel that turns)."""
        pairs = list(zip(self.motor_gain, self.motor_gain_uncertainty, strict=True))
        return tuple(max(1e-3, g - u) for g, u in pairs), tuple(g + u for g, u in pairs)


class World(BaseModel):
    """Every physical constant of the simulated world; frozen and hashable (a cache key)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    dt: float = Field(0.1, gt=0.0, le=10.0, description="control period, s (the agent's 10 Hz)")
    max_speed: float = Field(
        0.3, gt=0.0, le=10.0, description="wheel surface speed at command 1, m/s: 30 mm a step"
    )
    wheel_base: float = Field(
        0.11, gt=0.0, le=10.0, description="distance between the wheel contact points, m"
    )
    body_length: float = Field(0.165, gt=0.0, le=10.0, description="along the heading, m")
    body_width: float = Field(0.127, gt=0.0, le=10.0, description="across the heading, m")
    whisker_range: float | tuple[float, float, float, float, float] = Field(
        0.05,
        description="nominal trigger distance from the attachment point, m: one for all five "
        "whiskers or one per whisker, left to right",
    )
    motor_gain: tuple[float, float] = Field(
        (1.0, 1.0),
        description="nominal wheel gains [left, right]: a wheel's speed is command x gain x "
        "max_speed",
    )
    whisker_x: tuple[float, ...] = Field(
        (0.0825,) * N_WHISKERS, description="attachment points, forward in the body frame, m"
    )
    whisker_y: tuple[float, ...] = Field(
        (0.055, 0.0275, 0.0, -0.0275, -0.055),
        description="attachment points, leftward in the body frame, m (left to right)",
    )
    whisker_angles: tuple[float, ...] = Field(
        (60.0, 30.0, 0.0, -30.0, -60.0),
        description="whisker directions relative to the heading, degrees counter-clockwise",
    )
    stuck_after: int = Field(
        1,
        ge=1,
        le=1_000_000,
        description="consecutive blocked steps after which a robot is stuck for the trial",
    )
    gap_whisker_range: tuple[float, float] = Field(
        (0.025, 0.100),
        description="reality gap: each whisker's trigger distance drawn uniformly in this "
        "range, m (the paper's measured 25-100 mm)",
    )
    gap_motor_gain: float = Field(
        0.15,
        ge=0.0,
        lt=1.0,
        description="reality gap: each wheel's gain drawn in motor_gain x (1 +- this)",
    )
    gap_model: Literal["trial", "step"] = Field(
        "trial",
        description=(
            "reality gap: 'trial' draws each whisker's trigger distance once per trial; "
            "'step' draws each whisker's anew every step (noisy switches); wheel gains are "
            "per trial either way"
        ),
    )

    gap_robots: tuple[GapRobot, ...] = Field(
        (),
        max_length=MAX_GAP_ROBOTS,
        description="reality gap 'colony': each trial's robot is one of these calibrated robots "
        "(drawn uniformly), its whiskers and wheels drawn within their uncertainty in place of "
        "gap_whisker_range and gap_motor_gain",
    )

    @model_validator(mode="after")
    def _check(self) -> World:
        for name in ("whisker_x", "whisker_y", "whisker_angles"):
            values = getattr(self, name)
            if len(values) != N_WHISKERS:
                raise ValueError(
                    f"{name} needs {N_WHISKERS} values, one per whisker, got {len(values)}"
                )
            if not all(math.isfinite(v) and abs(v) <= 360.0 for v in values):
                raise ValueError(f"{name} must be finite and within +-360, got {values}")
        if not all(0.0 <= r <= 1.0 for r in self.whisker_ranges):
            raise ValueError(f"whisker_range must be within 0-1 m, got {self.whisker_range}")
        if not all(0.0 < g <= 10.0 for g in self.motor_gain):
            raise ValueError(f"motor_gain must be within (0, 10], got {self.motor_gain}")
        lo, hi = self.gap_whisker_range
        if not (0.0 <= lo <= hi <= 1.0):
            raise ValueError(
                f"gap_whisker_range must be 0 <= low <= high <= 1 m, got {self.gap_whisker_range}"
            )
        return self

    @property
    def whisker_ranges(self) -> tuple[float, ...]:
        """The five nominal trigger distances, left to right, m."""
        r = self.whisker_range
        return (r,) * N_WHISKERS if isinstance(r, float) else r

    @property
    def whisker_angle(self) -> tuple[float, ...]:
        """Whisker directions in radians (what the simulator computes with)."""
        return tuple(math.radians(a) for a in self.whisker_angles)

    @property
    def step_length(self) -> float:
        """Largest distance a robot covers in one step: max_speed x dt."""
        return self.max_speed * self.dt

    @property
    def half_diagonal(self) -> float:
        """Radius of the circle around the body: bounds every cell the body can touch."""
        return math.hypot(self.body_length / 2, self.body_width / 2)


def world_from_json(text: str | bytes) -> World:
    """The world in a JSON text: a World object, or any document with a `world` member (a
    run's config.json, a champion's best.json). ValueError naming the problem."""
    try:
        obj = json.loads(text)
    except (UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"invalid JSON: {exc}") from None
    if isinstance(obj, dict) and isinstance(obj.get("world"), dict):
        obj = obj["world"]
    if not isinstance(obj, dict):
        raise ValueError("expected a world object or a document with a 'world' member")
    return World.model_validate(obj)
