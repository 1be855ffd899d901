"""/api/robots: the colony's EvBots, controller pushes, stop, replacement policy, stuck ledger,
traces, calibration and the replay check.

Reads the `RobotService` the app's lifespan puts in `app.state.robots`.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response

from schemas.robots import (
    CalibrationOut,
    PushBody,
    PushOut,
    ReplacementBody,
    ReplayOut,
    RobotCalibration,
    RobotDetail,
    RobotOut,
    StuckEventsOut,
    TracesOut,
)
from server.robots.service import RobotService

router = APIRouter(prefix="/api/robots", tags=["robots"])


def get_robots(request: Request) -> RobotService:
    service: RobotService | None = getattr(request.app.state, "robots", None)
    if service is None:
        raise HTTPException(503, detail="the robot service is not running (no zenoh session)")
    return service


RobotsDep = Annotated[RobotService, Depends(get_robots)]


@router.get("", response_model=list[RobotOut])
def list_robots(robots: RobotsDep) -> list[RobotOut]:
    """Every robot ever seen, online or not."""
    return robots.robots()


@router.get("/{robot_id}", response_model=RobotDetail)
def get_robot(robots: RobotsDep, robot_id: str) -> RobotDetail:
    return robots.robot(robot_id)


@router.delete(
    "/{robot_id}",
    status_code=204,
    responses={404: {"description": "unknown robot"}, 409: {"description": "robot online"}},
)
def forget_robot(robots: RobotsDep, robot_id: str) -> Response:
    """Forget a stale robot: its registry entry, last report, stuck events and traces (the
    controllers' field statistics stay). Refused (409) while its agent is online."""
    robots.forget(robot_id)
    return Response(status_code=204)


@router.post("/{robot_id}/controller", response_model=PushOut)
def push_controller(robots: RobotsDep, robot_id: str, body: PushBody) -> PushOut:
    """Push a stored controller (`sha256`) or a run's: its best without `rank`, `elite` or `fit`
    (the validated champion once completed, else training rank 0), that training rank of its
    latest generation, that archive entry, or its candidate that roams most in the robot's
    calibrated world."""
    if (body.sha256 is None) == (body.run_id is None):
        raise HTTPException(422, detail="body: give exactly one of sha256 or run_id")
    return robots.push(
        robot_id,
        sha256=body.sha256,
        run_id=body.run_id,
        rank=body.rank,
        elite=body.elite,
        fit=body.fit,
    )


@router.post("/{robot_id}/stop", response_model=PushOut)
def stop_robot(robots: RobotsDep, robot_id: str) -> PushOut:
    """Motors to zero until the next push."""
    return robots.stop_robot(robot_id)


@router.put(
    "/{robot_id}/replacement",
    response_model=RobotDetail,
    responses={404: {"description": "unknown robot"}},
)
def set_replacement(robots: RobotsDep, robot_id: str, body: ReplacementBody) -> RobotDetail:
    """The robot's own replacement policy (`off`, `rank`), or null to follow the colony's
    (COLONY_REPLACEMENT); it applies from the robot's next stuck request."""
    return robots.set_replacement(robot_id, body.policy)


@router.get("/{robot_id}/stuck", response_model=StuckEventsOut)
def get_stuck_events(
    robots: RobotsDep,
    robot_id: str,
    limit: Annotated[int, Query(ge=1, le=100_000, description="newest events")] = 1000,
) -> StuckEventsOut:
    """The field ledger: each stuck event, the policy that served it, what was sent, and the
    steps the robot then ran before its next stuck event."""
    return robots.stuck_events(robot_id, limit)


@router.get("/{robot_id}/traces", response_model=TracesOut)
def get_traces(
    robots: RobotsDep,
    robot_id: str,
    limit: Annotated[int, Query(ge=1, le=100_000, description="newest samples")] = 1000,
) -> TracesOut:
    return robots.traces(robot_id, limit)


@router.get("/{robot_id}/replay", response_model=ReplayOut)
def replay(robots: RobotsDep, robot_id: str) -> ReplayOut:
    """Same whiskers into the same controller: are the motor commands bit-identical?"""
    return robots.replay(robot_id)


@router.get("/{robot_id}/calibration", response_model=CalibrationOut)
def get_calibration(robots: RobotsDep, robot_id: str) -> CalibrationOut:
    """The robot's physics as last fitted from its traces (404 when never calibrated)."""
    return robots.calibration(robot_id)


@router.post("/{robot_id}/calibration", response_model=CalibrationOut)
def post_calibration(robots: RobotsDep, robot_id: str, body: RobotCalibration) -> CalibrationOut:
    """Store a fit (`colony robot calibrate` posts its own); it replaces the earlier one."""
    return robots.set_calibration(robot_id, body)
