"""The robot side of the server on its zenoh session: `RobotService`, and its app hook.

`RobotService` lives on the server's one zenoh session (router mode). Zenoh callbacks only
enqueue; one service thread stores traces, answers replacement requests, tracks liveliness and
resolves push acknowledgements, so the database sees one writer from here. It checks that each
message comes from the robot it names and rate-limits stuck requests; its parts do the rest:
`traces.TraceIngest` (trace batches, tracker poses), `replacement.Replacements` (what a stuck
robot gets), `pushes.Pushes` (pushes, stops, acknowledgements) and `registry` (the robots as
the API shows them).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import zenoh
from fastapi import FastAPI
from sqlalchemy import Engine, delete, select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from evorobotics.strategies import Archive
from schemas.robots import (
    KEY_ACKS,
    KEY_REPLACE,
    KEY_ROBOTS_ALIVE,
    KEY_TRACES,
    KEY_TRACKER,
    CalibrationOut,
    FieldStats,
    PushAck,
    PushOut,
    Replacement,
    ReplacementPolicy,
    ReplayOut,
    RobotCalibration,
    RobotDetail,
    RobotOut,
    StuckEventsOut,
    StuckRequest,
    TraceAck,
    TracesOut,
    TrackerPose,
    decode_message,
    decode_trace,
    encode_message,
    robot_from_key,
    tracker_key,
)
from schemas.run import RunConfig
from schemas.wire import WireError
from server.core.errors import NotFoundError, ServerError
from server.core.logs import context
from server.core.models import Robot, utcnow
from server.robots.pushes import Pushes
from server.robots.registry import (
    calibration_of,
    field_stats,
    robot_detail,
    robot_summaries,
    stuck_ledger,
)
from server.robots.replacement import Ranker, Replacements
from server.robots.settings import POLICIES, RobotSettings
from server.robots.signing import Signer
from server.robots.store import RobotStateRow, StuckEventRow, TraceRow
from server.robots.traces import TraceIngest, TraceRefusedError, recent_samples, replay_stored

log = logging.getLogger(__name__)

INBOX_MAX = 10_000
"""Push acks and tracker poses (fire and forget) waiting beyond this many are dropped: a flood
of them neither fills memory nor holds other robots' traces long behind it."""
ACK_BURST, ACKS_PER_S = 20, 5.0
"""A robot's push acks: a token bucket (an honest agent acks each push once, pushes are rare);
acks beyond it are dropped before any database work."""


class RobotOnlineError(ServerError):
    """The robot holds a liveliness token: it cannot be forgotten while it runs (HTTP 409)."""

    status_code = 409


class RobotService:
    """Zenoh endpoints and store of the robot side, between `start()` and `close()`."""

    def __init__(
        self,
        session: zenoh.Session,
        engine_or_sessionmaker: Engine | sessionmaker[Session],
        settings: RobotSettings | None = None,
        signer: Signer | None = None,
        archives: Callable[[int], tuple[int, RunConfig, Archive]] | None = None,
        rank: Ranker | None = None,
    ) -> None:
        self.settings = settings or RobotSettings()
        self._zenoh = session
        self.sessions = (
            engine_or_sessionmaker
            if isinstance(engine_or_sessionmaker, sessionmaker)
            else sessionmaker(engine_or_sessionmaker, expire_on_commit=False)
        )
        self._inbox: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._online: set[str] = set()
        self._stuck_tokens: dict[str, tuple[float, float]] = {}
        """Per robot: stuck-request tokens left and when they were counted (service thread)."""
        self._ack_tokens: dict[str, tuple[float, float]] = {}
        """Per robot: push-ack tokens, likewise."""
        self.dropped = 0
        """Acks and tracker poses dropped: over a robot's ack budget, or the inbox full."""
        self._entities: list[Any] = []
        self._thread: threading.Thread | None = None
        self.poses_dropped = 0
        """Tracker poses dropped: malformed, out of order, or of a robot not online."""
        self.traces_received = 0
        """Trace samples stored (duplicates excluded); for benchmarks."""
        self._ingest = TraceIngest(self.sessions, self.settings, self.is_online)
        self._replacements = Replacements(self.sessions, self.settings, archives, rank)
        self._pushes = Pushes(
            self.sessions, self.settings, signer, self._replacements, self.is_online, self._publish
        )

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> RobotService:
        if self._thread is not None:
            raise RuntimeError("robot service already started")
        with self.sessions.begin() as db:
            for robot in db.scalars(select(Robot)):
                robot.status = "offline"
        z = self._zenoh
        self._entities = [
            z.declare_queryable(KEY_TRACES, lambda q: self._inbox.put(("trace", q))),
            z.declare_queryable(KEY_REPLACE, lambda q: self._inbox.put(("replace", q))),
            z.declare_subscriber(KEY_ACKS, lambda s: self._offer("ack", s)),
            z.declare_subscriber(KEY_TRACKER, lambda s: self._offer("pose", s)),
            z.liveliness().declare_subscriber(
                KEY_ROBOTS_ALIVE, lambda s: self._inbox.put(("alive", s)), history=True
            ),
        ]
        self._thread = threading.Thread(target=self._run, name="robot-service", daemon=True)
        self._thread.start()
        return self

    def close(self, timeout: float = 10.0) -> None:
        """Undeclare every endpoint and stop the service thread (the session stays open)."""
        for entity in self._entities:
            entity.undeclare()
        self._entities = []
        if self._thread is not None:
            self._inbox.put(("halt", None))
            self._thread.join(timeout)
            if self._thread.is_alive():
                raise RuntimeError("robot service thread did not stop")
            self._thread = None
        self._replacements.close()

    # ------------------------------------------------------------------ service thread

    def _offer(self, kind: str, sample: zenoh.Sample) -> None:
        """Queue a fire-and-forget message unless INBOX_MAX are waiting (then dropped)."""
        if self._inbox.qsize() >= INBOX_MAX:
            self.dropped += 1
            return
        self._inbox.put((kind, sample))

    def _run(self) -> None:
        while True:
            kind, item = self._inbox.get()
            if kind == "halt":
                return
            try:
                if kind == "trace":
                    self._on_trace(item)
                elif kind == "replace":
                    self._on_replace(item)
                elif kind == "ack":
                    self._on_ack(item)
                elif kind == "pose":
                    self._on_pose(item)
                else:
                    self._on_alive(item)
            except Exception:  # one bad message must not stop the robot side
                log.exception("robot service: handling %s failed", kind)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            robot = robot_from_key(str(sample.key_expr))
        except ValueError:
            log.warning("ignoring robot liveliness key %s", sample.key_expr)
            return
        online = sample.kind == zenoh.SampleKind.PUT
        with self.sessions.begin() as db:  # registered before it is online: pushable
            row = db.get(Robot, robot)
            if row is None:
                row = Robot(id=robot, status="online")
                db.add(row)
            row.status = "online" if online else "offline"
            row.last_seen = utcnow()
        with self._lock:
            was_online = robot in self._online
            (self._online.add if online else self._online.discard)(robot)
        if online != was_online:
            context(log, robot=robot).info("robot %s %s", robot, "online" if online else "offline")

    def _on_pose(self, sample: zenoh.Sample) -> None:
        """Keep a tracker's pose of an online robot, to be matched with its trace samples."""
        try:
            pose = decode_message(sample.payload.to_bytes())
            if not isinstance(pose, TrackerPose) or str(sample.key_expr) != tracker_key(pose.robot):
                raise WireError(f"not a TrackerPose of the robot its key names ({sample.key_expr})")
        except (WireError, ValueError) as exc:
            self.poses_dropped += 1
            log.debug("dropping a tracker pose: %s", exc)
            return
        if not self._ingest.track(pose):
            self.poses_dropped += 1

    def _on_ack(self, sample: zenoh.Sample) -> None:
        try:
            ack = decode_message(sample.payload.to_bytes())
        except WireError as exc:
            log.warning("dropping malformed ack: %s", exc)
            return
        if not isinstance(ack, PushAck):
            return
        if ack.robot != str(sample.key_expr).split("/")[2]:
            log.warning("dropping an ack for robot %s sent on %s", ack.robot, sample.key_expr)
            return
        if not self._allowed(self._ack_tokens, ack.robot, ACK_BURST, ACKS_PER_S):
            self.dropped += 1
            log.debug("dropping an ack of robot %s: over its budget", ack.robot)
            return
        robot_log = context(log, robot=ack.robot)
        if ack.accepted:
            robot_log.info("robot %s accepted push %s (%s)", ack.robot, ack.push_id, ack.sha256)
        else:
            robot_log.warning("robot %s rejected push %s: %s", ack.robot, ack.push_id, ack.reason)
        self._pushes.acknowledged(ack)

    def _on_trace(self, query: zenoh.Query) -> None:
        with query:
            try:
                batch = decode_trace(_payload(query))
                _check_sender(batch.robot, query)
            except WireError as exc:
                query.reply_err(f"malformed: {exc}".encode())
                return
            try:
                last, added = self._ingest.store(batch)
            except TraceRefusedError as exc:
                context(log, robot=batch.robot).warning(
                    "refusing a trace batch of robot %s (boot %d, steps %d-%d): %s",
                    batch.robot,
                    batch.boot,
                    batch.first,
                    batch.last,
                    exc,
                )
                query.reply_err(f"refused: {exc}".encode())
                return
            except SQLAlchemyError as exc:
                context(log, robot=batch.robot).error("storing traces failed: %s", exc)
                query.reply_err(b"not stored: the database failed; send the samples again")
                return
            self.traces_received += added
            ack = TraceAck(robot=batch.robot, last=last)
            query.reply(query.key_expr, encode_message(ack))

    def _on_replace(self, query: zenoh.Query) -> None:
        with query:
            try:
                request = decode_message(_payload(query))
                if not isinstance(request, StuckRequest):
                    raise WireError(f"expected a stuck request, got {request.kind}")
                _check_sender(request.robot, query)
            except WireError as exc:
                query.reply_err(f"malformed: {exc}".encode())
                return
            s = self.settings
            if not self._allowed(self._stuck_tokens, request.robot, s.stuck_burst, s.stuck_per_s):
                query.reply_err(
                    f"rate limited: more than {self.settings.stuck_burst} stuck requests at over "
                    f"{self.settings.stuck_per_s:g} a second; not recorded".encode()
                )
                return
            doc, reason = self._replacements.replace(request)
            text = doc.to_json() if doc else None
            seq, signature = self._pushes.sign("replacement", request.robot, request.nonce, text)
            reply = Replacement(
                robot=request.robot,
                document=text,
                reason=reason,
                seq=seq,
                signature=signature,
            )
            query.reply(query.key_expr, encode_message(reply))

    @staticmethod
    def _allowed(
        bucket: dict[str, tuple[float, float]], robot: str, burst: int, per_s: float
    ) -> bool:
        """Take a token from the robot's `bucket` (service thread only)."""
        now = time.monotonic()
        tokens, at = bucket.get(robot, (float(burst), now))
        tokens = min(float(burst), tokens + (now - at) * per_s)
        allowed = tokens >= 1.0
        bucket[robot] = (tokens - 1.0 if allowed else tokens, now)
        return allowed

    def _publish(self, key: str, payload: bytes) -> None:
        self._zenoh.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    # ------------------------------------------------------------------ API operations

    def is_online(self, robot_id: str) -> bool:
        with self._lock:
            return robot_id in self._online

    def robots(self) -> list[RobotOut]:
        with self.sessions() as db:
            return robot_summaries(db, self.is_online, self.settings.replacement)

    def robot(self, robot_id: str) -> RobotDetail:
        with self.sessions() as db:
            return robot_detail(
                db, robot_id=robot_id, is_online=self.is_online, settings=self.settings
            )

    def set_replacement(self, robot_id: str, policy: ReplacementPolicy | None) -> RobotDetail:
        """Give the robot its own replacement policy, or None to follow the colony's."""
        if policy is not None and policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES} or None, got {policy!r}")
        with self.sessions.begin() as db:
            row = db.get(Robot, robot_id)
            if row is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            row.replacement = policy
        context(log, robot=robot_id).info(
            "robot %s replacement policy: %s", robot_id, policy or "the colony's"
        )
        return self.robot(robot_id)

    def stuck_events(self, robot_id: str, limit: int = 1000) -> StuckEventsOut:
        """The robot's newest `limit` stuck events, oldest first: the field ledger."""
        with self.sessions() as db:
            return stuck_ledger(db, robot_id=robot_id, limit=limit, dt=self.settings.dt)

    def calibration(self, robot_id: str) -> CalibrationOut:
        """The robot's stored calibration; NotFoundError for an unknown or uncalibrated robot."""
        with self.sessions() as db:
            return calibration_of(db, robot_id=robot_id)

    def set_calibration(self, robot_id: str, calibration: RobotCalibration) -> CalibrationOut:
        """Store the robot's fitted physics (replacing any earlier fit)."""
        with self.sessions.begin() as db:
            row = db.get(Robot, robot_id)
            if row is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            row.calibration = calibration.model_dump_json()
            row.calibrated_at = utcnow()
        log.info(
            "robot %s calibrated: whiskers %s m, gains %s", robot_id,
            [round(r, 4) for r in calibration.whisker_range],
            [round(g, 4) for g in calibration.motor_gain],
        )  # fmt: skip
        return self.calibration(robot_id)

    def forget(self, robot_id: str) -> None:
        """Remove an offline robot: its registry row, last report, stuck events and traces.

        The field statistics stay: they are the controllers' record over the whole colony.
        """
        with self.sessions.begin() as db:
            if db.get(Robot, robot_id) is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            if self.is_online(robot_id):
                raise RobotOnlineError(f"robot {robot_id} is online: stop its agent first")
            for table in (TraceRow, StuckEventRow, RobotStateRow):
                db.execute(delete(table).where(table.robot_id == robot_id))
            db.execute(delete(Robot).where(Robot.id == robot_id))
        self._ingest.forget(robot_id)
        context(log, robot=robot_id).info("robot %s forgotten", robot_id)

    def push(
        self,
        robot_id: str,
        *,
        sha256: str | None = None,
        run_id: int | None = None,
        rank: int | None = None,
        elite: int | None = None,
        fit: bool = False,
        timeout: float | None = None,
    ) -> PushOut:
        """Push a stored controller (sha256) or a run's controller; wait for the ack
        (`Pushes.push`)."""
        return self._pushes.push(
            robot_id, sha256=sha256, run_id=run_id, rank=rank, elite=elite, fit=fit, timeout=timeout
        )

    def stop_robot(self, robot_id: str, timeout: float | None = None) -> PushOut:
        """Stop the robot's motors until the next push."""
        return self._pushes.stop(robot_id, timeout)

    def traces(self, robot_id: str, limit: int = 1000) -> TracesOut:
        """The newest `limit` stored samples, oldest first."""
        with self.sessions() as db:
            return recent_samples(db, robot_id=robot_id, limit=limit)

    def replay(self, robot_id: str) -> ReplayOut:
        """Feed the stored whiskers into the same controllers; compare motor commands bitwise."""
        with self.sessions() as db:
            return replay_stored(db, robot_id=robot_id)

    def field_stats(self, sha256: str) -> FieldStats | None:
        """Robot-hours and stuck events of a controller over the colony; None if never run."""
        with self.sessions() as db:
            return field_stats(db, sha256=sha256, dt=self.settings.dt)


def _check_sender(robot: str, query: zenoh.Query) -> None:
    """WireError unless `robot` is the robot whose key the query came on: zenoh's access
    control lets only that robot's credentials use its keys (docs/security.md)."""
    key = str(query.key_expr)
    if robot != key.split("/")[2]:
        raise WireError(f"robot {robot} may not send on {key}")


def _payload(query: zenoh.Query) -> bytes:
    return query.payload.to_bytes() if query.payload is not None else b""


def robot_service(
    settings: RobotSettings | None = None,
) -> Callable[[FastAPI, zenoh.Session], Callable[[], None]]:
    """A `create_app(..., services=[robot_service()])` hook: the service on the server's session.

    It uses the run manager's sessionmaker and the colony's replacement policy from its
    settings (COLONY_REPLACEMENT), and is exposed as `app.state.robots` for the routes.
    """

    def install(app: FastAPI, session: zenoh.Session) -> Callable[[], None]:
        signer = getattr(app.state, "signer", None)
        manager = app.state.manager
        tuned = replace(settings or RobotSettings(), replacement=manager.settings.replacement)
        service = RobotService(
            session, manager.sessions, tuned, signer, manager.archive, manager.scheduler.rank
        ).start()
        app.state.robots = service

        def close() -> None:
            app.state.robots = None
            service.close()

        return close

    return install
