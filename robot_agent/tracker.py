"""An overhead tracker for emulated robots: each physics step's true pose, published on the
robot's tracker key (`schemas.robots.tracker_key`) from the tracker's own zenoh session, as a
lab's camera bridge would publish what it sees. The server matches the poses to the robot's
trace samples by time and stores them as `pose_source: "tracker"` (docs/robots.md)."""

from __future__ import annotations

import logging
import math
import threading
from types import TracebackType

import zenoh

from robot_agent.emulator import BasicXEmulator
from schemas.robots import TrackerPose, encode_message, tracker_key

log = logging.getLogger(__name__)


class EmulatedTracker:
    """Publishes `emulator`'s body pose after every physics step, between `start()` and
    `stop()` (or `with`); the agent of that robot never sees these poses."""

    def __init__(self, session: zenoh.Session, robot_id: str, emulator: BasicXEmulator) -> None:
        self._session = session
        self._key = tracker_key(robot_id)
        self._robot = robot_id
        self._emulator = emulator
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._run, name="tracker", daemon=True)
        self.published = 0

    def start(self) -> EmulatedTracker:
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._halt.set()
        self._thread.join(timeout)

    def __enter__(self) -> EmulatedTracker:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def _run(self) -> None:
        seen = 0
        while not self._halt.is_set():
            got = self._emulator.wait_pose(seen + 1, timeout=0.2)
            if got is None:
                continue
            seen, at, (x, y, heading) = got
            theta = math.remainder(heading, math.tau)  # a heading may wind up many turns
            try:
                pose = TrackerPose(robot=self._robot, at=at, x=x, y=y, theta=theta)
                self._session.put(self._key, encode_message(pose))
                self.published += 1
            except (ValueError, zenoh.ZError) as exc:  # a pose beyond the limits, a closed session
                log.warning("tracker of %s: pose not published: %s", self._robot, exc)
