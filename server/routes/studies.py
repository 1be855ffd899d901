"""/api/studies: conditions x seeds runs with their statistics (docs/studies.md)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response, status

from schemas.study import StudyCreate, StudyOut
from server.routes.deps import StudiesDep

router = APIRouter(prefix="/api/studies", tags=["studies"])

StudyId = Annotated[int, Path(ge=0, le=2**63 - 1, description="a study id (64-bit)")]


@router.post("", status_code=status.HTTP_201_CREATED, response_model=StudyOut)
def create_study(studies: StudiesDep, body: StudyCreate) -> StudyOut:
    """Validate every condition (RunConfig and the server's limits), then queue its runs."""
    return studies.get(studies.create(body))


@router.get("", response_model=list[StudyOut])
def list_studies(studies: StudiesDep) -> list[StudyOut]:
    """Newest first, each in full."""
    return studies.all()


@router.get("/{study_id}", response_model=StudyOut)
def get_study(studies: StudiesDep, study_id: StudyId) -> StudyOut:
    return studies.get(study_id)


@router.post("/{study_id}/cancel", response_model=StudyOut)
def cancel_study(studies: StudiesDep, study_id: StudyId) -> StudyOut:
    """Cancel its unfinished runs; the completed ones and their statistics stay."""
    return studies.cancel(study_id)


@router.delete("/{study_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_study(studies: StudiesDep, study_id: StudyId) -> Response:
    """Cancel what still runs, then delete the study and its runs."""
    studies.delete(study_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
