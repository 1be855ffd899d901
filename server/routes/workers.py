"""/api/workers: the simulation workers the dispatcher knows, departed ones for a while.

Served from the dispatcher's memory, not a table: a worker's state only means something while
this server runs.
"""

from __future__ import annotations

from fastapi import APIRouter

from schemas.api import WorkerOut
from server.routes.deps import WorkersDep

router = APIRouter(tags=["workers"])


@router.get("/api/workers", response_model=list[WorkerOut])
def list_workers(workers: WorkersDep) -> list[WorkerOut]:
    """Every worker seen: idle, busy, or gone (listed until `gone_keep_s` after it left), and
    whether it is quarantined (it failed a spot-check: listed while this server runs)."""
    return workers
