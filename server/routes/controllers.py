"""/api/controllers: controller documents by sha256, with their field performance."""

from __future__ import annotations

import json

from fastapi import APIRouter, HTTPException, Request, Response

from server import crud
from server.deps import SessionDep

router = APIRouter(prefix="/api/controllers", tags=["controllers"])


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
def get_controller(request: Request, session: SessionDep, sha256: str) -> Response:
    row = crud.get_controller(session, sha256=sha256)
    if row is None:
        raise HTTPException(404, detail=f"no controller with sha256 {sha256}")
    robots = getattr(request.app.state, "robots", None)
    stats = robots.field_stats(row.sha256) if robots is not None else None
    body = json.loads(row.document)
    body["field"] = stats.model_dump(mode="json") if stats is not None else None
    return Response(
        content=json.dumps(body, sort_keys=True, separators=(",", ":")),
        media_type="application/json",
    )
