"""Exploration reports and robustness maps of stored controllers, computed once and kept.

One cache serves `GET /api/controllers/{sha}/evaluation`, `.../robustness` and the studies'
final metrics (`server.studies.service`), keyed by the document's text and the parameters: a report
is a pure function of them, and the dashboard, the CLI and a study asking again cost nothing.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from typing import NamedTuple

from evorobotics.document import ControllerDocument
from evorobotics.explore import explore
from evorobotics.robustness import robustness

EVALUATION_CACHE = 1024
"""Reports kept (a few kB each plus the document's text): every champion of the largest
study (`schemas.study.MAX_STUDY_RUNS`) fits."""


class Params(NamedTuple):
    """What an exploration report depends on besides the controller; defaults are
    `colony evaluate`'s."""

    poses: int = 1000
    steps: int = 1000
    maze: str = "paper"
    seed: int = 0
    reality_gap: bool = False


class MapParams(NamedTuple):
    """What a robustness map depends on besides the controller; defaults are
    `colony evaluate --robustness`'s."""

    poses: int = 50
    steps: int = 1000
    maze: str = "paper"
    seed: int = 0


class Evaluations:
    """A thread-safe LRU of report JSON by (document text, Params or MapParams)."""

    def __init__(self, size: int = EVALUATION_CACHE) -> None:
        self._size = size
        self._lock = threading.Lock()
        self._reports: OrderedDict[tuple[str, Params | MapParams], str] = OrderedDict()

    def peek(self, document: str, params: Params | MapParams) -> str | None:
        """The report if it is known, without computing it."""
        with self._lock:
            found = self._reports.get((document, params))
            if found is not None:
                self._reports.move_to_end((document, params))
            return found

    def report(self, document: str, params: Params | MapParams) -> str:
        """The report's JSON (the exploration or the map, plus the controller's `sha256`);
        CPU-bound on a miss (about 1 s of one core at the defaults). EvoError or ValueError
        on bad input."""
        found = self.peek(document, params)
        if found is not None:
            return found
        doc = ControllerDocument.from_json(document)
        if isinstance(params, MapParams):
            found_map = robustness(doc.spec, doc.weights, world=doc.world, **params._asdict())
            body = {**found_map.as_dict(), "sha256": doc.sha256}
        else:
            report = explore(doc.spec, doc.weights, world=doc.world, **params._asdict())
            body = {**report.as_dict(), "sha256": doc.sha256}
        text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
        with self._lock:
            self._reports[(document, params)] = text
            while len(self._reports) > self._size:
                self._reports.popitem(last=False)
        return text


EVALUATIONS = Evaluations()
"""The server's one cache (a process serves one store)."""
