"""The Colony page's map: the lab maze, and each robot's newest pose, recent path and stuck
events, read from the stored trace batches (their `times` and `poses`, docs/robots.md)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from evorobotics.maze import load_maze
from schemas.robots import ColonyMapOut, MapMaze, MapRobot, MapStuck
from server.core.models import Robot, aware
from server.robots.store import StuckEventRow, TraceRow
from server.robots.traces import trace_poses

PATH_SAMPLES = 600
"""Samples of recent path per robot by default: one minute at 10 Hz."""


def maze_out(spec: str) -> MapMaze:
    maze = load_maze(spec)
    rows = maze.text().splitlines()
    return MapMaze(
        name=maze.name,
        width=maze.width,
        height=maze.height,
        cell_size=maze.cell_size,
        rows=rows,
    )


def colony_map(
    db: Session, maze: str, is_online: Callable[[str], bool], samples: int = PATH_SAMPLES
) -> ColonyMapOut:
    """The maze named by the server's setting and every robot's last `samples` poses."""
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    robots = [
        _robot(db, robot_id, is_online(robot_id), samples)
        for robot_id in db.scalars(select(Robot.id).order_by(Robot.id))
    ]
    return ColonyMapOut(maze=maze_out(maze), robots=robots)


def _robot(db: Session, robot_id: str, online: bool, samples: int) -> MapRobot:
    """Newest batches first until `samples` poses of the newest batch's pose source (one
    frame: an agent's odometry starts where it was told, a tracker's in the maze); stuck events
    whose step lies in them."""
    newest_first = (TraceRow.boot.desc(), TraceRow.first.desc())
    mine = TraceRow.robot_id == robot_id
    # the batch counts alone first (the primary key's order), then only the batches needed
    counts = db.scalars(select(TraceRow.count).where(mine).order_by(*newest_first).limit(samples))
    needed = held = 0
    for count in counts:
        needed, held = needed + 1, held + count
        if held >= samples:
            break
    batches: list[tuple[TraceRow, np.ndarray, np.ndarray]] = []
    held = 0
    rows = db.scalars(select(TraceRow).where(mine).order_by(*newest_first).limit(needed))
    for row in rows:
        located = trace_poses(row)
        if located is None or (batches and row.pose_source != batches[0][0].pose_source):
            break  # no pose, or poses in another frame (odometry before a tracker saw it)
        batches.append((row, *located))
        held += row.count
        if held >= samples:
            break
    if not batches:
        return MapRobot(
            id=robot_id, online=online, pose_source=None, pose=None, at=None, path=[], stuck=[]
        )
    batches.reverse()
    poses = np.concatenate([p for _, _, p in batches])[-samples:]
    steps = np.concatenate([np.frombuffer(r.steps, "<i8") for r, _, _ in batches])[-samples:]
    boots = np.concatenate([np.full(r.count, r.boot) for r, _, _ in batches])[-samples:]
    newest_row, newest_times, _ = batches[-1]
    x, y, theta = (float(v) for v in poses[-1])
    return MapRobot(
        id=robot_id,
        online=online,
        pose_source=newest_row.pose_source,
        pose=(x, y, theta),
        at=float(newest_times[-1]),
        path=[(float(p[0]), float(p[1])) for p in poses],
        stuck=_stuck(db, robot_id, boots, steps, poses),
    )


def _stuck(
    db: Session, robot_id: str, boots: np.ndarray, steps: np.ndarray, poses: np.ndarray
) -> list[MapStuck]:
    """The robot's stuck events whose (boot, step) is one of the path's samples, oldest first."""
    where = {
        (boot, step): (float(pose[0]), float(pose[1]))
        for boot, step, pose in zip(boots.tolist(), steps.tolist(), poses, strict=True)
    }
    events = db.scalars(
        select(StuckEventRow)
        .where(StuckEventRow.robot_id == robot_id, StuckEventRow.boot >= int(boots.min()))
        .order_by(StuckEventRow.id.desc())
        .limit(len(where))
    )
    marks = []
    for event in events:
        spot = where.get((event.boot, event.step))
        if spot is not None:
            marks.append(
                MapStuck(
                    id=event.id,
                    at=(aware(event.at) or event.at).timestamp(),
                    step=event.step,
                    reason=event.reason,
                    x=spot[0],
                    y=spot[1],
                )
            )
    return marks[::-1]
