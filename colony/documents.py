"""Where `colony analyze` and `colony evaluate` get a controller: a file or a server's REST API."""

from __future__ import annotations

from pathlib import Path

import httpx
from pydantic import ValidationError

from colony.client import base_url_hint
from evorobotics.document import ControllerDocument
from evorobotics.errors import ControllerDocumentError
from schemas.robots import CalibrationOut
from schemas.world import World

TIMEOUT_S = 30.0


def _get(server: str, path: str) -> bytes:
    """The body of GET server+path; ValueError with the server's reason."""
    url = server.rstrip("/") + path
    try:
        response = httpx.get(url, timeout=TIMEOUT_S)
    except httpx.HTTPError as exc:
        raise ValueError(f"cannot reach {server}: {exc}") from None
    if response.is_error:
        try:
            detail = response.json()["detail"]
        except (ValueError, KeyError, TypeError):
            detail = response.text
        hint = base_url_hint(server, response.status_code)
        raise ValueError(f"GET {url}: {response.status_code} {detail}{hint}")
    return response.content


def fetch_document(
    server: str, *, run: int | None = None, sha: str | None = None
) -> ControllerDocument:
    """GET a run's best or a controller by sha256; ValueError with the server's reason."""
    if (run is None) == (sha is None):
        raise ValueError("give exactly one of run and sha")
    path = f"/api/runs/{run}/best" if run is not None else f"/api/controllers/{sha}"
    try:
        return ControllerDocument.from_json(_get(server, path))
    except ControllerDocumentError as exc:
        raise ValueError(f"GET {server.rstrip('/')}{path}: {exc}") from None


def robot_world(server: str, robot: str, world: World | None) -> World:
    """`world` (default World()) with the robot's calibrated whiskers and wheel gains
    (`GET /api/robots/{id}/calibration`); ValueError when it has none or is unknown."""
    body = _get(server, f"/api/robots/{robot}/calibration")
    try:
        fit = CalibrationOut.model_validate_json(body).calibration
    except ValidationError as exc:
        raise ValueError(f"robot {robot}'s calibration: {exc.errors()[0]['msg']}") from None
    return fit.world(world or World())


def load_document(
    controller: Path | None, server: str | None, run: int | None, sha: str | None
) -> ControllerDocument:
    """The document of CONTROLLER, or of `--server` with `--run`/`--sha`; ValueError saying
    which arguments are wrong or what is wrong with the document."""
    if controller is not None:
        if server is not None or run is not None or sha is not None:
            raise ValueError("give CONTROLLER or --server with --run/--sha, not both")
        try:
            return ControllerDocument.from_json(controller.read_bytes())
        except (OSError, ControllerDocumentError) as exc:
            raise ValueError(f"{controller}: {exc}") from None
    if server is None or (run is None) == (sha is None):
        raise ValueError("give a CONTROLLER file, or --server URL with exactly one of --run, --sha")
    return fetch_document(server, run=run, sha=sha)
