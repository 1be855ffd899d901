"""/api/controllers: controller documents by sha256."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Response

from server import crud
from server.deps import SessionDep

router = APIRouter(prefix="/api/controllers", tags=["controllers"])


@router.get(
    "/{sha256}",
    response_class=Response,
    responses={200: {"content": {"application/json": {}}, "description": "controller document"}},
)
def get_controller(session: SessionDep, sha256: str) -> Response:
    row = crud.get_controller(session, sha256=sha256)
    if row is None:
        raise HTTPException(404, detail=f"no controller with sha256 {sha256}")
    return Response(content=row.document, media_type="application/json")
