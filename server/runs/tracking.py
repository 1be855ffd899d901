"""TensorBoard event files of runs (optional; tensorboardX writes them, no TensorFlow needed).

A run's directory holds `fitness/best` and `fitness/mean` at each generation (step = the
generation) and, once it completes, its champion's validation (`validation/score`,
`validation/stuck`, `validation/roaming` at the last generation). The server writes them under
`COLONY_TENSORBOARD_DIR/run-ID`, `colony evolve --tensorboard DIR` into DIR; `tensorboard
--logdir` on the parent directory shows every run side by side. Event files are a view for
people, never read back: the store stays the record, and a generation written twice (a
server restarted mid-run recomputes the generation in flight) is merely shown twice.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable, Sequence
from pathlib import Path

from evorobotics.document import ControllerDocument
from schemas.run import ValidationScore
from server.runs.outbox import Written

log = logging.getLogger(__name__)

OPEN_WRITERS = 32
"""Event files a server keeps open; the least recently written beyond it is closed (a run
cancelled mid-way never reaches its last generation, which closes the others)."""


class RunEvents:
    """The event file of one run; every call ends with the file flushed to disk."""

    def __init__(self, directory: Path) -> None:
        from tensorboardX import SummaryWriter  # only when tracking: its import takes 0.3 s

        self._writer = SummaryWriter(logdir=str(directory), flush_secs=3600)

    def generation(self, generation: int, *, best: float, mean: float) -> None:
        self._writer.add_scalar("fitness/best", best, generation)
        self._writer.add_scalar("fitness/mean", mean, generation)
        self._writer.flush()

    def validation(self, generation: int, score: ValidationScore) -> None:
        for name in ("score", "stuck", "roaming"):
            self._writer.add_scalar(f"validation/{name}", getattr(score, name), generation)
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()


class Tracker:
    """The server's event files, one directory per run (`ROOT/run-ID`).

    A failure to write (a full disk, a read-only directory) is logged and never stops a run:
    the store, not the event files, is what a run must not lose.
    """

    def __init__(self, root: Path, champion: Callable[[int], ControllerDocument]) -> None:
        self._root = root
        self._champion = champion
        self._open: OrderedDict[int, RunEvents] = OrderedDict()
        self._failing = False

    def written(self, told: Sequence[Written]) -> None:
        """Record generations the store has just committed (oldest first)."""
        for item in told:
            try:
                self._record(item)
            except Exception as exc:  # tensorboardX raises whatever the file system does
                if not self._failing:
                    log.warning("TensorBoard event files not written under %s: %s", self._root, exc)
                self._failing = True
            else:
                self._failing = False

    def _record(self, item: Written) -> None:
        events = self._open.pop(item.run_id, None)
        if events is None:
            events = RunEvents(self._root / f"run-{item.run_id}")
        self._open[item.run_id] = events
        while len(self._open) > OPEN_WRITERS:
            self._open.popitem(last=False)[1].close()
        metrics, g = item.told.metrics, item.told.generation
        events.generation(g, best=metrics.best, mean=metrics.mean)
        if item.last:
            del self._open[item.run_id]
            try:
                validation = self._champion(item.run_id).validation
                if validation is not None:
                    events.validation(g, validation)
            finally:
                events.close()
