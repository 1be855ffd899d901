"""The scheduler's generations in flight: each live run's slots (its jobs) and their leases.

A run's pending slots are a heap (the lowest is leased first); a slot remembers the credentials
that erred on it and whose result filled it, so a quarantine can discard its result.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from evorobotics.evolution import RunLoop, job_slices
from schemas.wire import Job, JobKey
from server.runs.workers import credential


@dataclass
class Slot:
    """One job of a generation: individuals `start`:`stop`."""

    start: int
    stop: int
    status: str = "pending"
    """pending, leased or done."""
    erred: dict[str, tuple[str, str]] = field(default_factory=dict)
    """Credential -> (worker, error) of each whose evaluation of it erred: it is never leased
    to them again, and once it is done (so the job was fine) each error counts against them."""
    worker: str | None = None
    """Whose result filled it (done): discarded if that worker fails a spot-check."""


@dataclass
class Run:
    """A live run's generation in flight, cut into slots."""

    run_id: int
    loop: RunLoop
    running: bool
    slots: list[Slot]
    pending: list[int]
    """Heap of pending slot indices: the lowest is leased first."""
    fitness: np.ndarray
    components: np.ndarray
    descriptors: np.ndarray
    remaining: int
    served: int = 0
    """Sequence number of its last lease: the run served least recently goes first."""
    erred: bool = False
    """Some slot of this generation erred: leases skip the slots a credential erred on."""

    @classmethod
    def new(cls, run_id: int, loop: RunLoop, *, running: bool, served: int, size: int) -> Run:
        """`loop`'s current generation, cut into jobs of `size` individuals, all pending."""
        config = loop.config
        slots = [Slot(a, b) for a, b in job_slices(config.population, size)]
        return cls(
            run_id=run_id,
            loop=loop,
            running=running,
            slots=slots,
            pending=list(range(len(slots))),
            fitness=np.full(config.population, np.nan),
            components=np.full((config.population, config.trials, 4), np.nan),
            descriptors=np.full((config.population, 4), np.nan),
            remaining=len(slots),
            served=served,
        )

    def job(self, index: int, lease_s: float, *, span: int = 1) -> Job:
        """Slot `index` as a job (the whole run from its GA state when `span` > 1)."""
        slot = self.slots[index]
        loop = self.loop
        return Job(
            key=JobKey(run_id=self.run_id, generation=loop.generation, index=index),
            start=slot.start,
            stop=slot.stop,
            config=loop.config,
            genomes=loop.ask()[slot.start : slot.stop],
            span=span,
            state=loop.state.to_arrays() if span > 1 else None,
            lease_s=lease_s,
        )

    def pick(self, excluded: str | None) -> int | None:
        """The lowest pending slot not erred on by the credential `excluded`."""
        if not self.erred or excluded is None:
            return self.pending[0] if self.pending else None
        return min((i for i in self.pending if excluded not in self.slots[i].erred), default=None)

    def unpend(self, index: int) -> None:
        if self.pending[0] == index:
            heapq.heappop(self.pending)
        else:
            self.pending.remove(index)
            heapq.heapify(self.pending)

    def make_pending(self, index: int) -> None:
        slot = self.slots[index]
        if slot.status != "pending":
            slot.status = "pending"
            heapq.heappush(self.pending, index)

    def fill(
        self,
        index: int,
        worker: str,
        fitness: np.ndarray,
        components: np.ndarray,
        descriptors: np.ndarray,
    ) -> None:
        """Slot `index` is done: `worker`'s evaluation of it."""
        slot = self.slots[index]
        self.fitness[slot.start : slot.stop] = fitness
        self.components[slot.start : slot.stop] = components
        self.descriptors[slot.start : slot.stop] = descriptors
        slot.status = "done"
        slot.worker = worker
        self.remaining -= 1

    def discard(self, banned: str) -> int:
        """Return to pending each done slot a worker of the credential `banned` filled; how
        many."""
        discarded = 0
        for index, slot in enumerate(self.slots):
            if slot.status == "done" and slot.worker and credential(slot.worker) == banned:
                self.fitness[slot.start : slot.stop] = np.nan
                self.components[slot.start : slot.stop] = np.nan
                self.remaining += 1
                slot.worker = None
                self.make_pending(index)
                discarded += 1
        return discarded

    def stranded(self, max_attempts: int, takers: set[str] | None) -> list[int]:
        """Pending slots that erred on `max_attempts` credentials or on each of `takers` (the
        live credentials; None: one takes any job)."""
        return [
            index
            for index in self.pending
            if (erred := self.slots[index].erred)
            and (len(erred) >= max_attempts or (takers is not None and not takers - erred.keys()))
        ]


@dataclass
class Lease:
    """Who holds a job, until when."""

    key: JobKey
    worker: str
    deadline: float
    start: int
    stop: int
    leased_at: float = 0.0
    """When it was leased, on the scheduler's clock: its result measures the worker's speed."""
    span_left: int = 0
    """Generations of a span after this one."""
    asked_by_worker: bool = False
    """A span's generation the worker asked itself: its result must carry the digest."""
