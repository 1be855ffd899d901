"""Exploration reports and robustness maps of stored controllers, computed by jobs and kept.

One cache serves `GET /api/controllers/{sha}/evaluation`, `.../robustness` and the studies'
final metrics (`server.studies.service`), keyed by the document's text and the parameters: a
report is a pure function of them, and the dashboard, the CLI and a study asking again cost
nothing. A report missing from it is the scheduler's (`Scheduler.report`): jobs of its trials
that workers take like a run's (the in-process executors without workers), so the server
simulates none of it but a spot-check; asked again while in flight, it is the same report.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from concurrent.futures import Future
from typing import NamedTuple

from evorobotics.document import ControllerDocument
from evorobotics.reports import Report
from schemas.wire import ReportSpec, report_config
from schemas.world import World
from server.runs.scheduler import Scheduler

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


_Key = tuple[str, Params | MapParams]


class Evaluations:
    """A thread-safe LRU of report JSON by (document text, Params or MapParams), filled by
    the scheduler's report jobs."""

    def __init__(self, scheduler: Scheduler, size: int = EVALUATION_CACHE) -> None:
        self._scheduler = scheduler
        self._size = size
        self._lock = threading.Lock()
        self._reports: OrderedDict[_Key, str] = OrderedDict()

    def peek(self, document: str, params: Params | MapParams) -> str | None:
        """The report if it is known, without asking for it."""
        with self._lock:
            found = self._reports.get((document, params))
            if found is not None:
                self._reports.move_to_end((document, params))
            return found

    def request(self, document: str, params: Params | MapParams) -> Future[str]:
        """The future of the report's JSON (the exploration or the map, plus the controller's
        `sha256`): done at once when known, else when its jobs are (or fail: the server's own
        evaluation, or the server stopping). EvoError or ValueError on bad input."""
        known = Future[str]()
        found = self.peek(document, params)
        if found is not None:
            known.set_result(found)
            return known
        doc = ControllerDocument.from_json(document)
        config = report_config(doc.spec, doc.world or World(), params.maze, params.seed)
        if isinstance(params, MapParams):
            spec = ReportSpec(poses=params.poses, steps=params.steps)
            asked = self._scheduler.report("robustness", config, spec, doc.weights)
        else:
            spec = ReportSpec(
                poses=params.poses, steps=params.steps, reality_gap=params.reality_gap
            )
            asked = self._scheduler.report("explore", config, spec, doc.weights)

        def done(future: Future[Report]) -> None:
            try:
                body = {**future.result().as_dict(), "sha256": doc.sha256}
            except Exception as exc:  # the report failed: so does its JSON
                known.set_exception(exc)
                return
            text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
            with self._lock:
                self._reports[(document, params)] = text
                while len(self._reports) > self._size:
                    self._reports.popitem(last=False)
            known.set_result(text)

        asked.add_done_callback(done)
        return known

    def report(self, document: str, params: Params | MapParams, timeout: float) -> str:
        """The report's JSON, waiting at most `timeout` s for its jobs: TimeoutError past it
        (the jobs go on, and the report is kept once done); EvoError or ValueError on bad
        input, RuntimeError if it failed."""
        return self.request(document, params).result(timeout)
