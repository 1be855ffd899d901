"""The scheduler's generations in flight: each live run's slots (its jobs) and their leases.

A run's pending slots are a heap (the lowest is leased first); a slot remembers the credentials
that erred on it and whose result filled it, so a quarantine can discard its result. After its
last generation a run's slots are its champion's stage (`server.runs.choosing`): candidates to
validate or test poses, scored into `Run.scores`.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from evorobotics.evolution import RunLoop, job_slices, stage_robot_steps
from schemas.wire import Job, JobKey, Stage, score_columns
from server.runs.choosing import Choosing
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
    stage: Stage = "train"
    """What its slots are: the generation's individuals, or its champion's stage in hand."""
    choosing: Choosing | None = None
    """After the last generation: the champion being chosen, whose stage the slots are."""
    scores: np.ndarray | None = None
    """A stage's rows as scored (`Result.scores`), NaN until done."""

    @property
    def generation(self) -> int:
        """The generation its jobs are of (a champion's stage: the last one)."""
        return self.loop.generation if self.choosing is None else self.choosing.told.generation

    def robot_steps(self, n: int) -> int:
        """Robot-steps of a job of `n` rows of this run's slots."""
        return stage_robot_steps(self.loop.config, self.stage, n)

    def key(self, index: int) -> JobKey:
        return JobKey(run_id=self.run_id, generation=self.generation, index=index, stage=self.stage)

    @classmethod
    def choose(
        cls,
        run_id: int,
        loop: RunLoop,
        choosing: Choosing,
        *,
        running: bool,
        served: int,
        parts: int,
    ) -> Run:
        """The stage in hand of `choosing` cut into about `parts` jobs, all pending."""
        stage, n = choosing.stage, choosing.size
        if stage is None:
            raise ValueError(f"run {run_id}'s champion has no stage left to score")
        slots = [Slot(a, b) for a, b in job_slices(n, -(-n // max(1, min(parts, n))))]
        return cls(
            run_id=run_id,
            loop=loop,
            running=running,
            slots=slots,
            pending=list(range(len(slots))),
            fitness=np.empty(0),
            components=np.empty(0),
            descriptors=np.empty(0),
            remaining=len(slots),
            served=served,
            stage=stage,
            choosing=choosing,
            scores=np.full((n, score_columns(stage)), np.nan),
        )

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
        if self.choosing is not None:
            return Job(
                key=self.key(index),
                start=slot.start,
                stop=slot.stop,
                config=loop.config,
                genomes=self.choosing.genomes_for(slot.start, slot.stop),
                lease_s=lease_s,
            )
        return Job(
            key=self.key(index),
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
        self._done(slot, worker)

    def fill_scores(self, index: int, worker: str, scores: np.ndarray) -> Choosing | None:
        """Slot `index` of a champion's stage is done: `worker`'s scores of it. Once every slot
        is, the choice moves on to its next stage (`Choosing.advance`) and is returned."""
        if self.choosing is None or self.scores is None:
            raise ValueError(f"run {self.run_id} is evolving: it has no champion's stage")
        slot = self.slots[index]
        self.scores[slot.start : slot.stop] = scores
        self._done(slot, worker)
        if self.remaining:
            return None
        self.choosing.advance(self.scores)
        return self.choosing

    def _done(self, slot: Slot, worker: str) -> None:
        slot.status = "done"
        slot.worker = worker
        self.remaining -= 1

    def discard(self, banned: str) -> int:
        """Return to pending each done slot a worker of the credential `banned` filled; how
        many."""
        discarded = 0
        for index, slot in enumerate(self.slots):
            if slot.status == "done" and slot.worker and credential(slot.worker) == banned:
                if self.scores is not None:
                    self.scores[slot.start : slot.stop] = np.nan
                else:
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
