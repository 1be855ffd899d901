"""Trace batches into the store, and back out: what robots send, checked, kept and replayed.

A batch is stored only if the robot's agent could have sent it (consecutive steps, within what
the robot's clock allows since the boot began, contiguous with what was stored; docs/robots.md)
and acknowledged only once committed. Samples take an overhead tracker's poses where it saw the
robot (`TraceIngest.track`), which is what calibration trusts.

Retention: the newest `retention_samples` trace samples per robot are kept (whole batches are
deleted oldest first). Field statistics (steps run, stuck events per controller) are counters
updated as traces arrive, so they outlive the traces.
"""

from __future__ import annotations

import json
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta

import numpy as np
from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session, sessionmaker

from evorobotics import network
from evorobotics.document import ControllerDocument
from evorobotics.errors import ControllerDocumentError
from schemas.robots import (
    ESCAPE,
    TRACKER_MAX_AGE_S,
    ReplayOut,
    TraceBatch,
    TraceSample,
    TracesOut,
    TrackerPose,
)
from server.core.errors import NotFoundError
from server.core.models import Robot, aware, utcnow
from server.robots.settings import RobotSettings
from server.robots.store import (
    RobotStateRow,
    TraceRow,
    check_trace,
    field_row,
    served,
    trace_checksum,
)
from server.runs import crud

MAX_STEPS = 2**32
"""Steps of one boot beyond any agent's life (13 years at 10 Hz)."""
STEP_RATE_MARGIN = 1.25
"""An agent runs at most one step per dt (its loop never bursts to catch up); the margin covers
the clocks' disagreement, and makes a bound that is too tight catch up with a real robot."""
SLACK_STEPS = 100
"""Steps of slack on every time bound (transit, a step due at the instant of a batch)."""
MIN_BOOT_SECONDS = 0.1
"""An agent start takes longer than this: boot numbers cannot rise faster."""
TRACKED_POSES = 3000
"""Tracker poses kept per robot (5 min at 10 Hz): a trace batch arrives seconds after its
samples, so they are matched while the tracker's poses of that time are still here."""
TRACKED_ROBOTS = 64
"""Robots whose tracker poses are kept (online robots only): the memory of a lab's tracker."""
MAX_CLOCK_AHEAD = 300.0
"""Seconds a robot's clock may run ahead of the server's: a sample time beyond is refused."""
BOOTS_CACHED = 4
"""A robot's newest boots kept in memory; older ones are read again from the database."""


class TraceRefusedError(ValueError):
    """A trace batch the robot's agent could not have sent; nothing of it is stored."""


@dataclass(frozen=True)
class _Boot:
    """What is committed of one (robot, boot), and the bound on its steps.

    Steps run at most `STEP_RATE_MARGIN / dt` a second from (`anchor_step`, `anchor_at`), plus
    `backlog` samples the agent may hold from before the server heard of the boot.
    """

    last: int
    """Last step stored; -1 none."""
    at: float
    """Monotonic time `last` was committed."""
    anchor_step: int
    anchor_at: float
    backlog: int


class TraceIngest:
    """Stores trace batches and keeps tracker poses, on the robot service's thread (`forget`
    from any)."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        settings: RobotSettings,
        is_online: Callable[[str], bool],
    ) -> None:
        self._sessions = sessions
        self._settings = settings
        self._is_online = is_online
        self._tracked: dict[str, deque[tuple[float, float, float, float]]] = {}
        """robot -> its tracker poses (at, x, y, theta), oldest first."""
        self._stored: dict[str, int] = {}
        """Samples stored per robot, as committed."""
        self._allowance: dict[str, tuple[float, float]] = {}
        """robot -> (new samples it may send at once, when): every boot together runs at most
        one step per dt (a token bucket of `max_backlog` samples), so new boots in a burst
        cannot add samples faster than one robot's clock."""
        self._boots: dict[tuple[str, int], _Boot] = {}
        """Per (robot, boot), as committed."""

    def track(self, pose: TrackerPose) -> bool:
        """Keep a tracker's pose of an online robot (`_add` reads them); False when it is
        dropped: out of order, a replay, or of a robot not online."""
        track = self._tracked.get(pose.robot)
        if track is None:
            if not self._is_online(pose.robot) or len(self._tracked) >= TRACKED_ROBOTS:
                return False
            track = self._tracked[pose.robot] = deque(maxlen=TRACKED_POSES)
        if track and pose.at <= track[-1][0]:  # out of order, or a replay
            return False
        track.append((pose.at, pose.x, pose.y, pose.theta))
        return True

    def _tracker_poses(self, robot: str, times: np.ndarray) -> np.ndarray | None:
        """The tracker's pose of `robot` at each sample time (the newest at or before it), or
        None unless every sample has one at most TRACKER_MAX_AGE_S old."""
        track = self._tracked.get(robot)
        if not track:
            return None
        poses = np.array(track, dtype=np.float64)
        index = np.searchsorted(poses[:, 0], times, side="right") - 1
        if index[0] < 0 or not (times - poses[index, 0] <= TRACKER_MAX_AGE_S).all():
            return None
        return poses[index, 1:]

    def store(self, batch: TraceBatch) -> tuple[int, int]:
        """Store the samples not seen before; (the last step stored for (robot, boot), the
        samples added), once committed. TraceRefusedError for an implausible batch (nothing
        stored); a failed commit raises and leaves the caches as the database is, so the
        agent's re-sent samples land."""
        robot, key = batch.robot, (batch.robot, batch.boot)
        now = time.monotonic()
        try:
            with self._sessions.begin() as db:
                boot = self._boots.get(key) or self._load_boot(db, batch, now)
                self._check_plausible(batch, boot, now)
                new = batch.steps > boot.last
                allowance = self._spend(robot, int(new.sum()), now)
                self._report(db, batch)
                steps = batch.steps[new]
                if steps.shape[0] == 0:  # all seen before (a lost ack): acknowledged again
                    stored = self._stored.get(robot)
                else:
                    self._add(db, batch, new)
                    stored = self._retain(db, robot, int(steps.shape[0]))
        except TraceRefusedError:
            raise
        except Exception:
            self.forget(robot)
            raise
        # committed: only now may the caches (and so the acknowledgement) include the samples
        added = int(steps.shape[0])
        if added > 0:
            boot = replace(boot, last=int(steps[-1]), at=time.monotonic())
        self._allowance[robot] = (allowance, now)
        self._boots[key] = boot
        cached = sorted(b for r, b in list(self._boots) if r == robot)  # forget() may run
        for old in cached[:-BOOTS_CACHED]:  # a robot may start a new boot with every sample
            del self._boots[(robot, old)]
        if stored is not None:
            self._stored[robot] = stored
        return boot.last, added

    def _add(self, db: Session, batch: TraceBatch, new: np.ndarray) -> None:
        """The `new` samples of `batch` as a row, and their steps in the field statistics. The
        row keeps only the controllers its samples name (indices renumbered): a batch may list
        up to `MAX_TRACE_SAMPLES` of them, and a row's bytes must follow its samples."""
        steps, named = batch.steps[new], batch.controller[new]
        used = np.unique(named[named != ESCAPE])
        controllers = [batch.controllers[int(i)] for i in used]
        controller = np.where(named == ESCAPE, ESCAPE, np.searchsorted(used, named))
        poses, source = batch.poses[new], batch.pose_source
        tracked = self._tracker_poses(batch.robot, batch.times[new])
        if tracked is not None:  # from outside the robot: what calibration trusts
            poses, source = tracked, "tracker"
        row = TraceRow(
            robot_id=batch.robot,
            boot=batch.boot,
            first=int(steps[0]),
            last=int(steps[-1]),
            count=int(steps.shape[0]),
            controllers=json.dumps(controllers),
            steps=steps.astype("<i8").tobytes(),
            whiskers=batch.whiskers[new].tobytes(),
            motors=batch.motors[new].astype("<f8").tobytes(),
            controller=controller.astype("<i4").tobytes(),
            fresh=batch.fresh[new].tobytes(),
            times=batch.times[new].astype("<f8").tobytes(),
            poses=poses.astype("<f8").tobytes(),
            pose_source=source,
        )
        row.checksum = trace_checksum(row)
        db.add(row)
        given = served(db.get(Robot, batch.robot))
        for index, count in zip(*np.unique(controller, return_counts=True), strict=True):
            if index != ESCAPE and controllers[int(index)] in given:
                field_row(db, controllers[int(index)]).steps += int(count)

    def forget(self, robot: str) -> None:
        """Drop what is cached of `robot`: it is read again from the database when needed."""
        self._stored.pop(robot, None)
        for key in list(self._boots):  # a snapshot: the HTTP thread may call this too
            if key[0] == robot:
                self._boots.pop(key, None)

    def _load_boot(self, db: Session, batch: TraceBatch, now: float) -> _Boot:
        """What the database says of (robot, boot), with the bound its steps must keep."""
        robot, wall = batch.robot, time.time()

        def monotonic(at: datetime) -> float:
            stamp = (at if at.tzinfo else at.replace(tzinfo=UTC)).timestamp()
            return now - max(0.0, wall - stamp)

        mine = TraceRow.robot_id == robot
        this_boot = mine & (TraceRow.boot == batch.boot)
        latest = db.execute(
            select(TraceRow.last, TraceRow.received_at)
            .where(this_boot)
            .order_by(TraceRow.first.desc())
            .limit(1)
        ).first()
        if latest is not None:  # a known boot (the server restarted): the loosest bound
            earliest = db.execute(
                select(TraceRow.first, TraceRow.received_at)
                .where(this_boot)
                .order_by(TraceRow.first)
                .limit(1)
            ).first()
            assert earliest is not None
            return _Boot(
                last=int(latest[0]),
                at=monotonic(latest[1]),
                anchor_step=int(earliest[0]),
                anchor_at=monotonic(earliest[1]),
                backlog=self._settings.max_backlog,
            )
        newest = db.execute(
            select(func.max(TraceRow.boot), func.max(TraceRow.received_at)).where(mine)
        ).first()
        if newest is None or newest[1] is None:  # the robot's first batch ever
            return _Boot(-1, now, batch.first, now, self._settings.max_backlog)
        # a new boot starts after the robot's previous process last reported: its steps
        # cannot run ahead of the time since
        heard = monotonic(newest[1])
        starts = 1 + int((now - heard) / MIN_BOOT_SECONDS)
        if batch.boot > int(newest[0]) + starts:
            raise TraceRefusedError(
                f"boot {batch.boot} jumps from {newest[0]}: at most {starts} agent starts "
                f"fit in the {now - heard:.1f} s since that boot last reported"
            )
        return _Boot(-1, heard, 0, heard, 0)

    def _spend(self, robot: str, samples: int, now: float) -> float:
        """The robot's allowance after `samples` new ones at `now` (committed by the caller);
        TraceRefusedError if its clock cannot have made that many."""
        rate = STEP_RATE_MARGIN / self._settings.dt
        full = float(self._settings.max_backlog + SLACK_STEPS)
        left, at = self._allowance.get(robot, (full, now))
        left = min(full, left + (now - at) * rate)
        if samples > left:
            raise TraceRefusedError(
                f"{samples} new samples, more than the robot's clock allows now ({int(left)}): "
                f"all its boots together run at most {rate:g} steps a second"
            )
        return left - samples

    def _check_plausible(self, batch: TraceBatch, boot: _Boot, now: float) -> None:
        """TraceRefusedError unless the agent could have sent `batch` (docs/robots.md)."""
        if np.any(np.diff(batch.steps) != 1):
            raise TraceRefusedError("steps are not consecutive: an agent sends consecutive samples")
        if batch.last >= MAX_STEPS:
            raise TraceRefusedError(f"step {batch.last} is beyond {MAX_STEPS} of one boot")
        ahead_s = float(batch.times[-1]) - time.time()
        if ahead_s > MAX_CLOCK_AHEAD:
            raise TraceRefusedError(
                f"sample time is {ahead_s:.0f} s ahead of the server's clock (at most "
                f"{MAX_CLOCK_AHEAD:.0f} s)"
            )
        rate = STEP_RATE_MARGIN / self._settings.dt
        ahead = boot.anchor_step + boot.backlog + SLACK_STEPS + (now - boot.anchor_at) * rate
        if batch.last > ahead:
            raise TraceRefusedError(
                f"step {batch.last} is ahead of the robot's clock: at most {int(ahead)} for "
                f"boot {batch.boot} now"
            )
        if boot.last < 0:
            return
        lost = SLACK_STEPS + (now - boot.at + self._settings.request_slack) * rate
        if batch.first > boot.last + 1 + lost:
            raise TraceRefusedError(
                f"steps are not contiguous: step {batch.first} follows {boot.last}, and at most "
                f"{int(lost)} samples can have been dropped since"
            )

    def _report(self, db: Session, batch: TraceBatch) -> None:
        state = db.get(RobotStateRow, batch.robot)
        if state is None:
            state = RobotStateRow(robot_id=batch.robot, stuck_events=0)
            db.add(state)
        status = batch.status
        state.state, state.steps, state.boot = status.state, status.steps, batch.boot
        state.whiskers = "".join(str(int(b)) for b in batch.whiskers[-1])
        state.controller_sha256, state.serial_ok = status.sha256, status.serial_ok
        state.status, state.updated_at = status.model_dump_json(), utcnow()
        robot = db.get(Robot, batch.robot)
        if robot is None:
            robot = Robot(id=batch.robot, status="online")
            db.add(robot)
        robot.controller_sha256, robot.last_seen = status.sha256, utcnow()

    def _retain(self, db: Session, robot: str, added: int) -> int:
        """Delete the robot's oldest batches beyond `retention_samples` (newest batch kept, and
        every batch that arrived within `retention_window_s`); the samples it then has stored."""
        if robot in self._stored:
            stored = self._stored[robot] + added
        else:  # autoflush puts the new batch in the sum
            total = db.scalar(select(func.sum(TraceRow.count)).where(TraceRow.robot_id == robot))
            stored = int(total or 0)
        recent = utcnow() - timedelta(seconds=self._settings.retention_window_s)
        while stored > self._settings.retention_samples:
            oldest = db.execute(
                select(TraceRow.boot, TraceRow.first, TraceRow.count, TraceRow.received_at)
                .where(TraceRow.robot_id == robot)
                .order_by(TraceRow.boot, TraceRow.first)
                .limit(1)
            ).first()
            if oldest is None or stored - int(oldest[2]) < 1:
                break
            arrived = aware(oldest[3])
            if arrived is not None and arrived > recent:
                break
            db.execute(
                delete(TraceRow).where(
                    TraceRow.robot_id == robot,
                    TraceRow.boot == oldest[0],
                    TraceRow.first == oldest[1],
                )
            )
            stored -= int(oldest[2])
        return stored


def recent_samples(db: Session, *, robot_id: str, limit: int) -> TracesOut:
    """The robot's newest `limit` stored samples, oldest first."""
    if limit < 1:
        raise ValueError(f"limit must be >= 1, got {limit}")
    if db.get(Robot, robot_id) is None:
        raise NotFoundError(f"no robot with id {robot_id}")
    rows = list(
        db.scalars(
            select(TraceRow)
            .where(TraceRow.robot_id == robot_id)
            .order_by(TraceRow.boot.desc(), TraceRow.first.desc())
        )
    )
    samples: list[TraceSample] = []
    for row in rows:
        samples = _samples(row) + samples
        if len(samples) >= limit:
            break
    return TracesOut(robot=robot_id, samples=samples[-limit:])


def replay_stored(db: Session, *, robot_id: str) -> ReplayOut:
    """Feed the robot's stored whiskers into the same controllers; compare motor commands
    bitwise (`replay_trace`)."""
    if db.get(Robot, robot_id) is None:
        raise NotFoundError(f"no robot with id {robot_id}")
    rows = list(
        db.scalars(
            select(TraceRow)
            .where(TraceRow.robot_id == robot_id)
            .order_by(TraceRow.boot, TraceRow.first)
        )
    )
    docs: dict[str, ControllerDocument | None] = {}
    for row in rows:
        for sha in json.loads(row.controllers):
            if sha not in docs:
                stored = crud.get_controller(db, sha256=sha)
                docs[sha] = _document(stored.document) if stored else None
    return replay_trace(robot_id, rows, docs)


def _document(text: str) -> ControllerDocument | None:
    try:
        return ControllerDocument.from_json(text)
    except ControllerDocumentError:
        return None


def _arrays(row: TraceRow) -> tuple[np.ndarray, ...]:
    check_trace(row)
    n = row.count
    return (
        np.frombuffer(row.steps, "<i8"),
        np.frombuffer(row.whiskers, "|u1").reshape(n, 5),
        np.frombuffer(row.motors, "<f8").reshape(n, 2),
        np.frombuffer(row.controller, "<i4"),
        np.frombuffer(row.fresh, "|b1"),
    )


def trace_poses(row: TraceRow) -> tuple[np.ndarray, np.ndarray] | None:
    """The batch's sample times (n,) and poses (n, 3); None for a batch stored without."""
    if row.times is None or row.poses is None:
        return None
    check_trace(row)
    return np.frombuffer(row.times, "<f8"), np.frombuffer(row.poses, "<f8").reshape(row.count, 3)


def _samples(row: TraceRow) -> list[TraceSample]:
    shas = json.loads(row.controllers)
    steps, whiskers, motors, controller, fresh = _arrays(row)
    located = trace_poses(row)
    return [
        TraceSample(
            boot=row.boot,
            step=int(steps[i]),
            whiskers="".join(str(int(b)) for b in whiskers[i]),
            motors=(float(motors[i, 0]), float(motors[i, 1])),
            controller_sha256=None if controller[i] == ESCAPE else shas[int(controller[i])],
            fresh=bool(fresh[i]),
            at=None if located is None else float(located[0][i]),
            pose=None if located is None else _pose(located[1][i]),
            pose_source=None if located is None else row.pose_source,
        )
        for i in range(row.count)
    ]


def _pose(values: np.ndarray) -> tuple[float, float, float]:
    return float(values[0]), float(values[1]), float(values[2])


def replay_trace(
    robot: str, rows: list[TraceRow], docs: dict[str, ControllerDocument | None]
) -> ReplayOut:
    """The replay check over stored batches in (boot, first) order, with their controllers.

    A controller's run is replayed from its fresh sample on; see docs/robots.md.
    """
    checked = segments = skipped = mismatches = 0
    first: dict[str, object] | None = None
    doc: ControllerDocument | None = None
    state = np.empty(0)
    prev: tuple[int, int] | None = None
    for row in rows:
        shas = json.loads(row.controllers)
        steps, whiskers, motors, controller, fresh = _arrays(row)
        for i in range(row.count):
            here = (row.boot, int(steps[i]))
            contiguous = prev is not None and here == (prev[0], prev[1] + 1)
            prev = here
            if controller[i] == ESCAPE:
                doc = None
                skipped += 1
                continue
            sha = shas[int(controller[i])]
            if fresh[i]:
                doc = docs.get(sha)
                if doc is not None:
                    state = network.reset(doc.spec, 1)
                    segments += 1
            elif doc is None or doc.sha256 != sha or not contiguous:
                doc = None  # its fresh start was not retained, or samples were lost
            if doc is None:
                skipped += 1
                continue
            weights = doc.weights[np.newaxis, :]
            out, state = network.step(doc.spec, weights, whiskers[i : i + 1].astype(float), state)
            expected = network.motor_commands(doc.spec, out)[0]
            checked += 1
            if expected.tobytes() != motors[i].tobytes():
                mismatches += 1
                if first is None:
                    first = {
                        "boot": row.boot,
                        "step": here[1],
                        "sent": motors[i].tolist(),
                        "replayed": expected.tolist(),
                        "controller_sha256": sha,
                    }
    return ReplayOut(
        robot=robot,
        identical=checked > 0 and mismatches == 0,
        checked=checked,
        segments=segments,
        skipped=skipped,
        mismatches=mismatches,
        first_mismatch=first,
    )
