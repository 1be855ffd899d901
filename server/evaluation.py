"""Exploration reports of stored controllers (`evorobotics.explore`), computed once and kept.

One cache serves `GET /api/controllers/{sha}/evaluation` and the studies' final metrics
(`server.studies`), keyed by the document's text and the parameters: a report is a pure
function of them, and the dashboard, the CLI and a study asking again cost nothing.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from typing import NamedTuple

from evorobotics.document import ControllerDocument
from evorobotics.explore import explore

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


class Evaluations:
    """A thread-safe LRU of report JSON by (document text, Params)."""

    def __init__(self, size: int = EVALUATION_CACHE) -> None:
        self._size = size
        self._lock = threading.Lock()
        self._reports: OrderedDict[tuple[str, Params], str] = OrderedDict()

    def peek(self, document: str, params: Params) -> str | None:
        """The report if it is known, without computing it."""
        with self._lock:
            found = self._reports.get((document, params))
            if found is not None:
                self._reports.move_to_end((document, params))
            return found

    def report(self, document: str, params: Params) -> str:
        """The report's JSON (the exploration plus the controller's `sha256`); CPU-bound on a
        miss (about 1 s of one core at the defaults). EvoError or ValueError on bad input."""
        found = self.peek(document, params)
        if found is not None:
            return found
        doc = ControllerDocument.from_json(document)
        result = explore(
            doc.spec,
            doc.weights,
            poses=params.poses,
            steps=params.steps,
            maze=params.maze,
            seed=params.seed,
            reality_gap=params.reality_gap,
            world=doc.world,
        )
        body = {**result.as_dict(), "sha256": doc.sha256}
        text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
        with self._lock:
            self._reports[(document, params)] = text
            while len(self._reports) > self._size:
                self._reports.popitem(last=False)
        return text


EVALUATIONS = Evaluations()
"""The server's one cache (a process serves one store)."""
