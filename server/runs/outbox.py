"""Told generations on their way from the scheduler to the store, and the runs to fail.

The store writes what `take` gives and reports it `written`; a run whose oldest unwritten
generation waits past `store_lag_s` leases nothing more (`lags`), so a store that blocks
stops its runs within that much evolution. No lock: the scheduler calls it under its own.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from evorobotics.document import ControllerDocument
from evorobotics.evolution import Told
from schemas.run import RunConfig
from server.runs.policy import Policy


@dataclass(frozen=True)
class Written:
    """A told generation waiting to be stored."""

    run_id: int
    config: RunConfig
    told: Told
    champion: ControllerDocument | None = None
    """The run's champion (`server.runs.choosing`) with its last generation, whose storing
    completes the run; None for any other generation."""
    stored: bool = False
    """The generation is in the store already (a run an older server completed, or stopped,
    without naming its champion): only the champion is written."""

    @property
    def last(self) -> bool:
        """The run's last generation: storing it completes the run."""
        return self.champion is not None


class Outbox:
    """Told generations not yet taken, when each not yet written was told, runs to fail."""

    def __init__(self, policy: Policy, clock: Callable[[], float]) -> None:
        self._policy = policy
        self._clock = clock
        self._told: list[Written] = []
        self._unwritten: dict[int, deque[float]] = {}
        """run id -> when each generation told and not yet written was told, oldest first."""
        self.told_many = threading.Event()
        """Set when a run has `write_now` generations unwritten: the store should write now."""
        self._failed: dict[int, str] = {}

    def tell(self, item: Written) -> None:
        """`item` was told: it waits for the store."""
        self._told.append(item)
        times = self._unwritten.setdefault(item.run_id, deque())
        times.append(self._clock())
        if len(times) >= self._policy.write_now:
            self.told_many.set()

    def take(self) -> list[Written]:
        """The generations told since the last call, oldest first."""
        told, self._told = self._told, []
        return told

    def written(self, told: list[Written]) -> None:
        """The store has `told` (or dropped it, its run being over)."""
        for item in told:
            times = self._unwritten.get(item.run_id)
            if times:
                times.popleft()
            if not times:
                self._unwritten.pop(item.run_id, None)

    def put_back(self, told: list[Written]) -> None:
        """Told generations the store refused: first in line for the next `take`."""
        self._told[:0] = told

    def lags(self, run_id: int) -> bool:
        """Whether the run's oldest unwritten generation has waited past `store_lag_s`."""
        times = self._unwritten.get(run_id)
        return times is not None and self._clock() - times[0] > self._policy.store_lag_s

    def drop(self, run_id: int) -> None:
        """The run is over: its unwritten generations hold nothing back."""
        self._unwritten.pop(run_id, None)

    def fail(self, run_id: int, why: str) -> None:
        self._failed[run_id] = why

    def take_failed(self) -> dict[int, str]:
        """The runs (id -> why) failed since the last call."""
        failed, self._failed = self._failed, {}
        return failed

    def put_back_failed(self, failed: dict[int, str]) -> None:
        """Failures the store could not record: taken again next time."""
        self._failed = failed | self._failed
