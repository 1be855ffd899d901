"""Settings of the robot side, and which replacement policy a robot gets: every module of
`server.robots` reads them, so they sit below all of them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import get_args

from schemas.robots import DEFAULT_REPLACEMENT, PolicySource, ReplacementPolicy
from schemas.world import World

POLICIES: tuple[ReplacementPolicy, ...] = get_args(ReplacementPolicy)


@dataclass(frozen=True)
class RobotSettings:
    """Retention and timing of the robot side."""

    retention_samples: int = 36_000
    """Trace samples kept per robot (one hour at 10 Hz), beyond those of `retention_window_s`."""
    retention_window_s: float = 3600.0
    """Samples that arrived within this long are never evicted: no burst of a robot's
    credential evicts what it had acknowledged (its arrivals are bounded by its clock)."""
    push_timeout: float = 3.0
    """Seconds a push waits for the robot's acknowledgement (it applies at a step boundary)."""
    recent_failures: int = 5
    """A stuck robot gets no controller it failed with in its last this-many stuck events."""
    dt: float = World().dt
    """Seconds of one control step, for robot-hours and the plausibility of trace steps."""
    max_backlog: int = 36_000
    """Samples an agent may buffer before the server hears of its boot (its buffer_samples)."""
    request_slack: float = 5.0
    """Seconds a trace batch may spend in flight (the agent's request timeout, with margin)."""
    replacement: ReplacementPolicy = DEFAULT_REPLACEMENT
    """The colony's replacement policy: a robot without its own gets this one."""
    stuck_burst: int = 20
    stuck_per_s: float = 1.0
    """Stuck requests a robot may send at once, and then per second (a token bucket): an honest
    agent sends one per escape (1.4 s at 10 Hz); beyond, a request is refused unrecorded."""
    stuck_retention: int = 10_000
    """Stuck events kept per robot (the oldest go first): the field ledger's depth."""

    def __post_init__(self) -> None:
        if self.replacement not in POLICIES:
            raise ValueError(f"replacement must be one of {POLICIES}, got {self.replacement!r}")
        if min(self.retention_samples, self.recent_failures, self.max_backlog) < 1:
            raise ValueError("retention_samples, recent_failures and max_backlog must be >= 1")
        if not self.retention_window_s >= 0:
            raise ValueError(f"retention_window_s must be >= 0, got {self.retention_window_s}")
        if not self.push_timeout > 0 or not self.dt > 0 or not self.request_slack >= 0:
            raise ValueError("push_timeout and dt must be > 0, request_slack >= 0")
        if min(self.stuck_burst, self.stuck_retention) < 1 or not self.stuck_per_s > 0:
            raise ValueError("stuck_burst and stuck_retention must be >= 1, stuck_per_s > 0")


def effective_policy(
    own: str | None, colony: ReplacementPolicy
) -> tuple[ReplacementPolicy, PolicySource]:
    """The policy a robot's stuck requests get: its own if it has one, else the colony's."""
    for policy in POLICIES:
        if own == policy:
            return policy, "robot"
    return colony, "colony"
