"""Dead reckoning for a real EvBot: the pose integrated from the wheel commands it was sent.

A real BasicX does not know where it is (it has no `P` request), so the agent integrates the
commands with the simulator's own body model (`evorobotics.sim.move`, nominal wheel gains, no
walls): the same kinematics a virtual robot's true pose follows. It drifts with every wheel's
real gain and every blocked move, so traces label it `pose_source: "odometry"`.
"""

from __future__ import annotations

import numpy as np

from evorobotics.sim import move
from robot_agent.serial_protocol import MOTOR_FULL_SCALE, motor_units
from schemas.world import World


class Odometry:
    """The pose of one robot from `start`, advanced one control step at a time."""

    def __init__(self, start: tuple[float, float, float], world: World) -> None:
        self.world = world
        self._pose = np.array([start], dtype=np.float64)
        self._gain = np.ones((1, 2))

    @property
    def pose(self) -> tuple[float, float, float]:
        """x, y (metres) and heading (radians, in [-pi, pi))."""
        x, y, theta = self._pose[0]
        return float(x), float(y), float(theta)

    def advance(self, left: float, right: float) -> None:
        """One step (`world.dt`) with the commands as the wire carried them (1/1000 steps)."""
        motors = np.array(
            [[motor_units(left) / MOTOR_FULL_SCALE, motor_units(right) / MOTOR_FULL_SCALE]]
        )
        self._pose = move(self._pose, motors, self._gain, self.world)
