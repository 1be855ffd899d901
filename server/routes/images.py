"""PNG figures of a run's best controller for the dashboard: its network (Figs 1, 5) and its
paths from unseen start poses (Fig 6), drawn by evorobotics.plots.

A figure is a pure function of the controller (and, for paths, the run's config), so it is
cached by sha256 and served with that as ETag: the browser re-asks every generation and gets
304 until the best controller changes.
"""

from __future__ import annotations

import tempfile
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Header, HTTPException, Response

from evorobotics.document import ControllerDocument
from schemas.run import RunConfig
from server.routes.deps import ManagerDep, SessionDep
from server.runs import crud

router = APIRouter(prefix="/api/runs", tags=["runs"])

Figure = Literal["network", "paths"]
CACHE_SIZE = 64
"""Rendered PNGs kept (each 20-80 kB)."""

_cache: OrderedDict[tuple[str, str, str], bytes] = OrderedDict()
_cache_lock = threading.Lock()
_draw_lock = threading.Lock()
"""pyplot keeps global figure state: one drawing at a time."""


def render(figure: Figure, document: ControllerDocument, config: RunConfig) -> bytes:
    """The PNG bytes of one figure (matplotlib is imported only when a figure is asked)."""
    from evorobotics import plots

    with _draw_lock, tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{figure}.png"
        if figure == "network":
            plots.network_plot(document.spec, document.weights, path)
        else:
            plots.paths_plot(config, document, path)
        return path.read_bytes()


def cached_png(figure: Figure, document: ControllerDocument, config: RunConfig) -> bytes:
    """`render` through a small LRU keyed by figure, sha256 and (for paths) the config."""
    key = (figure, document.sha256, config.model_dump_json() if figure == "paths" else "")
    with _cache_lock:
        if key in _cache:
            _cache.move_to_end(key)
            return _cache[key]
    png = render(figure, document, config)
    with _cache_lock:
        _cache[key] = png
        while len(_cache) > CACHE_SIZE:
            _cache.popitem(last=False)
    return png


@router.get(
    "/{run_id}/best/{figure}.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "the figure"}},
)
def best_figure(
    manager: ManagerDep,
    session: SessionDep,
    run_id: int,
    figure: Figure,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """`network` or `paths` of the run's best controller (`GET /api/runs/{id}/best`)."""
    document = manager.best(run_id)
    run = crud.get_run(session, run_id=run_id)
    if run is None:
        raise HTTPException(404, detail=f"run {run_id} vanished")
    etag = f'"{figure}-{document.sha256}"'
    headers = {"ETag": etag, "Cache-Control": "no-cache"}
    if if_none_match == etag:
        return Response(status_code=304, headers=headers)
    config = RunConfig.model_validate_json(run.config)
    return Response(cached_png(figure, document, config), media_type="image/png", headers=headers)
