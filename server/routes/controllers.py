"""/api/controllers: controller documents by sha256, their field performance and exploration."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Query, Request, Response

from evorobotics.errors import EvoError
from evorobotics.maze import is_shipped_or_generated, load_maze
from schemas.api import ErrorOut
from server.routes.deps import EvaluationsDep, ManagerDep, SessionDep
from server.runs import crud
from server.studies.evaluation import Evaluations, MapParams, Params

router = APIRouter(prefix="/api/controllers", tags=["controllers"])

Sha = Annotated[
    str, Path(description="a controller's sha256, or an unambiguous prefix of 8+ hex digits")
]
"""404 when no stored controller has it, 422 when malformed or ambiguous (`crud.find_controller`)."""

MAX_EVALUATION_POSES = 1000
MAX_EVALUATION_STEPS = 2000
MAX_EVALUATION_ROBOT_STEPS = 1_000_000
"""poses x steps of one evaluation request: about 1 s of one core (docs/api.md)."""
MAX_ROBUSTNESS_POSES = 200
MAX_ROBUSTNESS_ROBOT_STEPS = 100_000
"""poses x steps per cell of one robustness map: 4.9 M robot-steps over its 49 cells."""
REPORT_WAIT_S = 60.0
"""How long a request waits for its report's jobs before a 503 (they go on: asked again, the
report is the cached one)."""
_WAITED: dict[str, Any] = {
    "model": ErrorOut,
    "description": f"the report's jobs took over {REPORT_WAIT_S:.0f} s (Retry-After), or it "
    "failed (the server's own evaluation, or the server stopping)",
}


@router.get(
    "/{sha256}",
    response_class=Response,
    responses={
        200: {
            "content": {"application/json": {}},
            "description": "controller document plus a `field` member: robot-hours and stuck "
            "events per hour over the colony (null if it never ran on a robot)",
        }
    },
)
def get_controller(request: Request, session: SessionDep, sha256: Sha) -> Response:
    row = crud.find_controller(session, sha256=sha256)
    robots = getattr(request.app.state, "robots", None)
    stats = robots.field_stats(row.sha256) if robots is not None else None
    body = json.loads(row.document)
    body["field"] = stats.model_dump(mode="json") if stats is not None else None
    return Response(
        content=json.dumps(body, sort_keys=True, separators=(",", ":")),
        media_type="application/json",
    )


@router.get(
    "/{sha256}/evaluation",
    response_class=Response,
    responses={
        200: {
            "content": {"application/json": {}},
            "description": "the controller's exploration report (evorobotics.explore, "
            "docs/explore.md) plus its `sha256`",
        },
        503: _WAITED,
    },
)
def get_evaluation(
    manager: ManagerDep,
    evaluations: EvaluationsDep,
    sha256: Sha,
    poses: Annotated[int, Query(ge=1, le=MAX_EVALUATION_POSES)] = 1000,
    steps: Annotated[int, Query(ge=1, le=MAX_EVALUATION_STEPS)] = 1000,
    maze: Annotated[str, Query(min_length=1, max_length=4096)] = "paper",
    seed: Annotated[int, Query(ge=0, lt=2**63)] = 0,
    reality_gap: bool = False,
) -> Response:
    """Jobs that workers take (about 1 s of CPU at most): a sync route, so it waits for them
    in the threadpool."""
    with manager.sessions() as session:  # closed before the computation, not held through it
        document = crud.find_controller(session, sha256=sha256).document
    if poses * steps > MAX_EVALUATION_ROBOT_STEPS:
        raise HTTPException(
            422,
            detail=f"poses x steps: {poses} x {steps} = {poses * steps} exceeds the limit of "
            f"{MAX_EVALUATION_ROBOT_STEPS} robot steps",
        )
    return _report(evaluations, document, maze, Params(poses, steps, maze, seed, reality_gap))


@router.get(
    "/{sha256}/robustness",
    response_class=Response,
    responses={
        200: {
            "content": {"application/json": {}},
            "description": "the controller's robustness map (evorobotics.robustness, "
            "docs/explore.md): roaming and stuck per whisker range x wheel gain ratio, plus "
            "its `sha256`",
        },
        503: _WAITED,
    },
)
def get_robustness(
    manager: ManagerDep,
    evaluations: EvaluationsDep,
    sha256: Sha,
    poses: Annotated[int, Query(ge=1, le=MAX_ROBUSTNESS_POSES)] = 50,
    steps: Annotated[int, Query(ge=1, le=MAX_EVALUATION_STEPS)] = 1000,
    maze: Annotated[str, Query(min_length=1, max_length=4096)] = "paper",
    seed: Annotated[int, Query(ge=0, lt=2**63)] = 0,
) -> Response:
    """Jobs that workers take (up to a few seconds of CPU): a sync route, so it waits for them
    in the threadpool."""
    with manager.sessions() as session:
        document = crud.find_controller(session, sha256=sha256).document
    if poses * steps > MAX_ROBUSTNESS_ROBOT_STEPS:
        raise HTTPException(
            422,
            detail=f"poses x steps: {poses} x {steps} = {poses * steps} exceeds the limit of "
            f"{MAX_ROBUSTNESS_ROBOT_STEPS} robot steps per cell",
        )
    return _report(evaluations, document, maze, MapParams(poses, steps, maze, seed))


def _report(
    evaluations: Evaluations, document: str, maze: str, params: Params | MapParams
) -> Response:
    """The report or map of a stored document (cached, or its jobs awaited); 422 naming a bad
    maze or parameter, 503 (Retry-After) while workers compute it or when it failed."""
    # a bare path would read a file on the server
    if not is_shipped_or_generated(maze):
        raise HTTPException(
            422, detail=f"maze: {maze!r} is not a shipped maze, gen:SIZE:SEED or maze text"
        )
    try:
        load_maze(maze)
    except (EvoError, ValueError) as exc:
        raise HTTPException(422, detail=f"maze: {exc}") from None
    try:
        body = evaluations.report(document, params, REPORT_WAIT_S)
    except (EvoError, ValueError) as exc:
        raise HTTPException(422, detail=str(exc)) from None
    except TimeoutError:
        raise HTTPException(
            503,
            detail=f"the report's jobs took over {REPORT_WAIT_S:.0f} s (no worker free?): they "
            "go on, ask again",
            headers={"Retry-After": "10"},
        ) from None
    except RuntimeError as exc:
        raise HTTPException(503, detail=str(exc)) from None
    return Response(content=body, media_type="application/json")
