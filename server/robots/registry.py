"""The robot registry as the API shows it: each robot's summary and detail, its calibration,
its stuck ledger, a controller's field statistics, and the colony's calibrated robots as a
run's reality gap. Queries only: `RobotService` owns the sessions and who is online."""

from __future__ import annotations

import json
from collections.abc import Callable
from datetime import datetime
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from schemas.robots import (
    CalibrationOut,
    FieldStats,
    FieldWindow,
    LedgerController,
    ReplacementPolicy,
    RobotCalibration,
    RobotDetail,
    RobotOut,
    StuckEventOut,
    StuckEventsOut,
)
from schemas.run import RunConfig
from schemas.world import MAX_GAP_ROBOTS
from server.core.errors import NotFoundError
from server.core.models import Controller, Robot, aware
from server.robots.settings import POLICIES, RobotSettings, effective_policy
from server.robots.store import FieldStatsRow, RobotStateRow, StuckEventRow, TraceRow


def robot_summaries(
    db: Session, is_online: Callable[[str], bool], colony: ReplacementPolicy
) -> list[RobotOut]:
    """Every robot ever seen, by id: the one robot view of /api/robots and /api/colony;
    `colony` is the colony's replacement policy."""
    rows = list(db.scalars(select(Robot).order_by(Robot.id)))
    states = {s.robot_id: s for s in db.scalars(select(RobotStateRow))}
    return [_summary(r, states.get(r.id), is_online(r.id), colony) for r in rows]


def _summary(
    row: Robot, state: RobotStateRow | None, online: bool, colony: ReplacementPolicy
) -> RobotOut:
    last = state.updated_at if state else row.last_seen
    policy, source = effective_policy(row.replacement, colony)
    return RobotOut(
        id=row.id,
        online=online,
        state=(state.state if state else "idle") if online else "offline",
        controller_sha256=row.controller_sha256,
        steps=state.steps if state else 0,
        stuck_events=state.stuck_events if state else 0,
        last_seen=aware(last),
        replacement=policy,
        replacement_source=source,
    )


def robot_detail(
    db: Session, *, robot_id: str, is_online: Callable[[str], bool], settings: RobotSettings
) -> RobotDetail:
    """The robot's summary, the origin of its controller, its link and, once calibrated, its
    field record before and since."""
    row = db.get(Robot, robot_id)
    if row is None:
        raise NotFoundError(f"no robot with id {robot_id}")
    state = db.get(RobotStateRow, robot_id)
    summary = _summary(row, state, is_online(row.id), settings.replacement)
    origin: dict[str, Any] = {}
    if summary.controller_sha256:
        ctrl = db.get(Controller, summary.controller_sha256)
        if ctrl is not None:
            origin = json.loads(ctrl.document).get("provenance", {})
            origin["run"] = ctrl.run_id
            origin["generation"] = ctrl.generation
    status = json.loads(state.status) if state else {}
    calibrated: dict[str, Any] = {}
    if row.calibration is not None and row.calibrated_at is not None:
        at = row.calibrated_at
        calibrated = {
            "calibration": RobotCalibration.model_validate_json(row.calibration),
            "calibrated_at": aware(at),
            "before_calibration": _window(db, robot_id, None, at, settings.dt),
            "since_calibration": _window(db, robot_id, at, None, settings.dt),
        }
    return RobotDetail(
        **summary.model_dump(),
        controller_run=_int_or_none(origin.get("run")),
        controller_rank=_int_or_none(origin.get("rank")),
        controller_generation=_int_or_none(origin.get("generation")),
        whiskers=state.whiskers if state else "00000",
        boot=state.boot if state else 0,
        link={"zenoh": "online" if summary.online else "offline", **status},
        **calibrated,
    )


def _window(
    db: Session, robot_id: str, since: datetime | None, until: datetime | None, dt: float
) -> FieldWindow:
    """The robot's retained samples and stuck events that arrived in [since, until)."""
    samples = select(func.coalesce(func.sum(TraceRow.count), 0)).where(
        TraceRow.robot_id == robot_id
    )
    events = select(func.count(StuckEventRow.id)).where(StuckEventRow.robot_id == robot_id)
    if since is not None:
        samples = samples.where(TraceRow.received_at >= since)
        events = events.where(StuckEventRow.at >= since)
    if until is not None:
        samples = samples.where(TraceRow.received_at < until)
        events = events.where(StuckEventRow.at < until)
    hours = int(db.scalar(samples) or 0) * dt / 3600.0
    stuck = int(db.scalar(events) or 0)
    return FieldWindow(
        robot_hours=hours, stuck_events=stuck, stuck_per_hour=stuck / hours if hours else None
    )


def _int_or_none(value: object) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def calibration_of(db: Session, *, robot_id: str) -> CalibrationOut:
    """The robot's stored calibration; NotFoundError for an unknown or uncalibrated robot."""
    row = db.get(Robot, robot_id)
    if row is None:
        raise NotFoundError(f"no robot with id {robot_id}")
    if row.calibration is None or row.calibrated_at is None:
        raise NotFoundError(f"robot {robot_id} has no calibration (colony robot calibrate)")
    return CalibrationOut(
        robot=robot_id,
        stored_at=aware(row.calibrated_at),
        calibration=RobotCalibration.model_validate_json(row.calibration),
    )


def stuck_ledger(db: Session, *, robot_id: str, limit: int, dt: float) -> StuckEventsOut:
    """The robot's newest `limit` stuck events, oldest first: the field ledger."""
    if limit < 1:
        raise ValueError(f"limit must be >= 1, got {limit}")
    if db.get(Robot, robot_id) is None:
        raise NotFoundError(f"no robot with id {robot_id}")
    rows = list(
        db.scalars(
            select(StuckEventRow)
            .where(StuckEventRow.robot_id == robot_id)
            .order_by(StuckEventRow.id.desc())
            .limit(limit)
        )
    )
    events = [_event_out(r) for r in reversed(rows)]
    return StuckEventsOut(robot=robot_id, events=events, controllers=_ledger(events, dt))


def _ledger(events: list[StuckEventOut], dt: float) -> list[LedgerController]:
    """Per controller of `events`: the steps run after the events that left the robot with
    it, and the events in which it stuck; longest run first."""
    steps: dict[str, int] = {}
    stuck: dict[str, int] = {}
    for e in events:
        ran = e.replacement_sha256 or e.controller_sha256
        if ran is not None and e.steps_run is not None:
            steps[ran] = steps.get(ran, 0) + e.steps_run
        if e.controller_sha256 is not None:
            stuck[e.controller_sha256] = stuck.get(e.controller_sha256, 0) + 1
    shas = sorted(steps.keys() | stuck.keys(), key=lambda s: (-steps.get(s, 0), s))
    return [
        LedgerController(
            sha256=s,
            steps_run=steps.get(s, 0),
            seconds_run=steps.get(s, 0) * dt,
            stuck_events=stuck.get(s, 0),
        )
        for s in shas
    ]


def _event_out(row: StuckEventRow) -> StuckEventOut:
    policy = next((p for p in POLICIES if p == row.policy), None)
    at = aware(row.at)
    return StuckEventOut(
        id=row.id,
        at=at.timestamp() if at else 0.0,
        step=row.step,
        reason=row.reason,
        controller_sha256=row.controller_sha256,
        policy=policy,
        replacement_sha256=row.replacement_sha256,
        answer=row.answer,
        steps_run=row.steps_run,
    )


def with_colony_gap(db: Session, config: RunConfig) -> RunConfig:
    """`config` with the colony's calibrated robots as its gap when it asks for `reality_gap:
    "colony"` and names none (stored with the run: it stays a function of its config);
    NotFoundError when no robot is calibrated."""
    if config.reality_gap != "colony" or config.world.gap_robots:
        return config
    rows = db.scalars(
        select(Robot).where(Robot.calibration.is_not(None)).order_by(Robot.id).limit(MAX_GAP_ROBOTS)
    ).all()
    robots = tuple(
        RobotCalibration.model_validate_json(r.calibration).gap_robot(r.id)
        for r in rows
        if r.calibration is not None
    )
    if not robots:
        raise NotFoundError(
            "reality_gap 'colony' draws from the calibrated robots, and no robot is calibrated: "
            "colony robot calibrate ROBOT"
        )
    world = config.world.model_copy(update={"gap_robots": robots})
    return RunConfig.model_validate({**config.model_dump(), "world": world.model_dump()})


def field_stats(db: Session, *, sha256: str, dt: float) -> FieldStats | None:
    """Robot-hours and stuck events of a controller over the colony; None if never run."""
    row = db.get(FieldStatsRow, sha256.lower())
    if row is None:
        return None
    hours = row.steps * dt / 3600.0
    return FieldStats(
        sha256=row.sha256,
        robot_hours=hours,
        stuck_events=row.stuck_events,
        stuck_per_hour=row.stuck_events / hours if hours > 0 else None,
    )
