"""The scheduler's work in flight: each live run's slots (its jobs), each report's and each
ranking's, and their leases.

A run's, a report's or a ranking's pending slots are a heap (the lowest is leased first); a
slot remembers the credentials that erred on it and whose result filled it, so a quarantine can
discard its result. After its last generation a run's slots are its champion's stage
(`server.runs.choosing`): candidates to validate or test poses, scored into `Run.scores`. A
report's slots are trials of a controller's exploration report or robustness map
(`evorobotics.reports`), scored into `Report.scores` and assembled into its `future`; a
ranking's, a run's candidates validated in a robot's world (`evorobotics.evolution
.rank_in_world`), scored into `Rank.scores` and ranked into its `future`.
"""

from __future__ import annotations

import hashlib
import heapq
import secrets
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from evorobotics.errors import EvoError
from evorobotics.evolution import (
    Ranked,
    RunLoop,
    Validated,
    job_slices,
    ranked,
    ranking_config,
    stage_robot_steps,
)
from evorobotics.maze import load_maze
from evorobotics.reports import Report as Assembled
from evorobotics.reports import assemble, implausible
from schemas.run import RunConfig
from schemas.wire import (
    REPORT_ROBOT_STEPS,
    Job,
    JobKey,
    ReportSpec,
    ReportStage,
    Stage,
    rank_candidates,
    report_trials,
    score_columns,
)
from schemas.world import World
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
    lapsed: set[str] = field(default_factory=set)
    """Credentials whose lease of it reached its deadline without a result: never leased to
    them again, but no error against them."""
    worker: str | None = None
    """Whose result filled it (done): discarded if that worker fails a spot-check."""

    def excluded(self) -> set[str]:
        """The credentials it is never leased to: those that erred on it or let it lapse."""
        return self.erred.keys() | self.lapsed


@dataclass(kw_only=True)
class Slotted:
    """Work cut into slots, leased lowest first: a run's generation or stage, or a report."""

    slots: list[Slot]
    pending: list[int]
    """Heap of pending slot indices: the lowest is leased first."""
    remaining: int
    running: bool = True
    served: int = 0
    """Sequence number of its last lease: the work served least recently goes first."""
    erred: bool = False
    """Some slot erred or lapsed: leases skip the slots a credential erred on or let lapse."""
    stage: Stage = "train"
    """What its slots are: a generation's individuals, a champion's stage, or a report's."""
    scores: np.ndarray | None = None
    """A stage's rows as scored (`Result.scores`), NaN until done."""

    def pick(self, excluded: str | None) -> int | None:
        """The lowest pending slot the credential `excluded` neither erred on nor let lapse."""
        if not self.erred or excluded is None:
            return self.pending[0] if self.pending else None
        return min(
            (i for i in self.pending if excluded not in self.slots[i].excluded()), default=None
        )

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

    def _done(self, slot: Slot, worker: str) -> None:
        slot.status = "done"
        slot.worker = worker
        self.remaining -= 1

    def _fill_scores(self, index: int, worker: str, scores: np.ndarray) -> bool:
        """Slot `index` of a stage is done: `worker`'s scores of it; whether every slot is."""
        if self.scores is None:
            raise ValueError(f"{self.stage} slots carry no scores")
        slot = self.slots[index]
        self.scores[slot.start : slot.stop] = scores
        self._done(slot, worker)
        return not self.remaining

    def _clear(self, slot: Slot) -> None:
        """Forget what a done slot's result said."""
        if self.scores is not None:
            self.scores[slot.start : slot.stop] = np.nan

    def discard(self, banned: str) -> int:
        """Return to pending each done slot a worker of the credential `banned` filled; how
        many."""
        discarded = 0
        for index, slot in enumerate(self.slots):
            if slot.status == "done" and slot.worker and credential(slot.worker) == banned:
                self._clear(slot)
                self.remaining += 1
                slot.worker = None
                self.make_pending(index)
                discarded += 1
        return discarded

    def stranded(self, max_attempts: int, takers: set[str] | None) -> list[int]:
        """Pending slots that erred on or lapsed with `max_attempts` credentials or each of
        `takers` (the live credentials; None: one takes any job)."""
        return [
            index
            for index in self.pending
            if (tried := self.slots[index].excluded())
            and (len(tried) >= max_attempts or (takers is not None and not takers - tried))
        ]


_CHOOSE = secrets.SystemRandom()
"""Draws the individuals to check: a worker cannot predict them from the run's seed."""


def _stage_slots(n: int, parts: int) -> list[Slot]:
    """`n` rows of a stage in about `parts` slots."""
    return [Slot(a, b) for a, b in job_slices(n, -(-n // max(1, min(parts, n))))]


@dataclass(kw_only=True)
class Run(Slotted):
    """A live run's generation in flight, cut into slots."""

    run_id: int
    loop: RunLoop
    fitness: np.ndarray
    components: np.ndarray
    descriptors: np.ndarray
    choosing: Choosing | None = None
    """After the last generation: the champion being chosen, whose stage the slots are."""
    check_rows: list[np.ndarray] = field(default_factory=list)
    """Per slot of a generation cut into several: individuals of it (drawn with `secrets`)
    that the next slot's job evaluates too (`Job.checks`), its spot-check by whoever takes
    that job."""
    checked: dict[int, tuple[str, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)
    """Slot -> the worker that evaluated its `check_rows` and their fitness, components and
    descriptors as it did."""
    shown: dict[int, set[str]] = field(default_factory=dict)
    """Slot -> the credentials leased the job that carries its `check_rows` (the next slot's),
    whatever became of the lease: they know which of its rows are checked."""

    @property
    def config(self) -> RunConfig:
        return self.loop.config

    @property
    def label(self) -> str:
        return f"run {self.run_id}"

    @property
    def order(self) -> tuple[int, int, int]:
        """Leases go to the lowest: reports first, then the run served least recently."""
        return (1, self.served, self.run_id)

    @property
    def report(self) -> ReportSpec | None:
        """A run's jobs are no report's."""
        return None

    def genomes_for(self, start: int, stop: int) -> np.ndarray:
        """The genomes of a stage's rows start:stop (`Choosing.genomes_for`)."""
        if self.choosing is None:
            raise ValueError(f"run {self.run_id} is evolving: it has no champion's stage")
        return self.choosing.genomes_for(start, stop)

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
        slots = _stage_slots(n, parts)
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
    def new(
        cls, run_id: int, loop: RunLoop, *, running: bool, served: int, size: int, checks: int
    ) -> Run:
        """`loop`'s current generation, cut into jobs of `size` individuals, all pending; cut
        into several, each slot's `checks` individuals go to the next slot's job."""
        config = loop.config
        slots = [Slot(a, b) for a, b in job_slices(config.population, size)]
        check_rows = []
        if checks and len(slots) > 1:
            check_rows = [
                np.array(
                    sorted(_CHOOSE.sample(range(s.start, s.stop), min(checks, s.stop - s.start)))
                )
                for s in slots
            ]
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
            check_rows=check_rows,
        )

    def checks_of(self, index: int) -> np.ndarray | None:
        """The rows slot `index`'s job evaluates too: the previous slot's `check_rows`."""
        if not self.check_rows or self.choosing is not None:
            return None
        return self.check_rows[index - 1]

    def show(self, index: int, worker: str) -> None:
        """Slot `index`'s job, with the rows it checks, is leased to `worker` (`shown`)."""
        if self.checks_of(index) is not None:
            self.shown.setdefault((index - 1) % len(self.slots), set()).add(credential(worker))

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
            checks=None if (rows := self.checks_of(index)) is None else loop.ask()[rows],
            lease_s=lease_s,
        )

    def fill(
        self,
        index: int,
        worker: str,
        fitness: np.ndarray,
        components: np.ndarray,
        descriptors: np.ndarray,
    ) -> None:
        """Slot `index` is done: `worker`'s evaluation of it, then of the rows it checks
        (`checks_of`)."""
        slot = self.slots[index]
        n = slot.stop - slot.start
        self.fitness[slot.start : slot.stop] = fitness[:n]
        self.components[slot.start : slot.stop] = components[:n]
        self.descriptors[slot.start : slot.stop] = descriptors[:n]
        if self.checks_of(index) is not None:
            checked = (index - 1) % len(self.slots)
            self.checked[checked] = (worker, fitness[n:], components[n:], descriptors[n:])
        self._done(slot, worker)

    def fill_scores(self, index: int, worker: str, scores: np.ndarray) -> Choosing | None:
        """Slot `index` of a champion's stage is done: `worker`'s scores of it. Once every slot
        is, the choice moves on to its next stage (`Choosing.advance`) and is returned."""
        if self.choosing is None or self.scores is None:
            raise ValueError(f"run {self.run_id} is evolving: it has no champion's stage")
        if not self._fill_scores(index, worker, scores):
            return None
        self.choosing.advance(self.scores)
        return self.choosing

    def _clear(self, slot: Slot) -> None:
        if self.scores is not None:
            super()._clear(slot)
        else:
            self.fitness[slot.start : slot.stop] = np.nan
            self.components[slot.start : slot.stop] = np.nan


@dataclass(kw_only=True)
class Asked(Slotted):
    """Work the server asks for itself, of no run: a report or a ranking. Its number is a
    digest of what it computes, so the same work asked twice (or after a restart) is one."""

    report_id: int
    config: RunConfig

    @property
    def order(self) -> tuple[int, int, int]:
        """Before runs (someone waits for each), least recently served first."""
        return (0, self.served, self.report_id)

    def key(self, index: int) -> JobKey:
        return JobKey(run_id=self.report_id, generation=0, index=index, stage=self.stage)

    @property
    def report(self) -> ReportSpec | None:
        """A report's size; a ranking's jobs carry none."""
        return None

    def genomes_for(self, start: int, stop: int) -> np.ndarray:
        """The genomes of rows start:stop."""
        raise NotImplementedError

    def job(self, index: int, lease_s: float, *, span: int = 1) -> Job:
        """Slot `index` as a job (never a span)."""
        slot = self.slots[index]
        return Job(
            key=self.key(index),
            start=slot.start,
            stop=slot.stop,
            config=self.config,
            genomes=self.genomes_for(slot.start, slot.stop),
            report=self.report,
            lease_s=lease_s,
        )


def _digest(*parts: str | np.ndarray) -> int:
    """An asked work's number: 63 bits of the SHA-256 of what it computes."""
    text = "\n".join(p for p in parts if isinstance(p, str)).encode()
    arrays = b"".join(p.tobytes() for p in parts if isinstance(p, np.ndarray))
    return int.from_bytes(hashlib.sha256(text + arrays).digest()[:8], "little") >> 1


def _check_maze(config: RunConfig) -> None:
    """A bad maze fails the asker now, not every worker later."""
    try:
        load_maze(config.maze)
    except EvoError as exc:
        raise ValueError(f"maze: {exc}") from exc


@dataclass(kw_only=True)
class Report(Asked):
    """A controller's report in flight (`evorobotics.reports`): its trials cut into slots,
    scored into `scores`, assembled into `future` once all are. Its `config` is
    `schemas.wire.report_config`: the controller's network and world, the report's maze and
    seed."""

    spec: ReportSpec
    genome: np.ndarray
    """(1, n_weights): the controller's weights."""
    future: Future[Assembled] = field(default_factory=Future)

    @classmethod
    def new(
        cls,
        stage: ReportStage,
        config: RunConfig,
        spec: ReportSpec,
        weights: np.ndarray,
        *,
        served: int,
        parts: int,
    ) -> Report:
        """The report cut into about `parts` jobs, all pending. ValueError for a bad maze,
        weights or size."""
        genome = np.ascontiguousarray(weights, dtype="<f8").reshape(1, -1)
        if genome.shape[1] != config.network_spec.weight_count:
            raise ValueError(
                f"{genome.shape[1]} weights for a network of {config.network_spec.weight_count}"
            )
        _check_maze(config)
        n = report_trials(stage, spec.poses)
        if n * spec.steps > REPORT_ROBOT_STEPS:
            raise ValueError(
                f"a report of {n} trials x {spec.steps} steps exceeds the limit of "
                f"{REPORT_ROBOT_STEPS} robot steps"
            )
        slots = _stage_slots(n, parts)
        return cls(
            report_id=_digest(stage, config.model_dump_json(), spec.model_dump_json(), genome),
            config=config,
            spec=spec,
            genome=genome,
            slots=slots,
            pending=list(range(len(slots))),
            remaining=len(slots),
            served=served,
            stage=stage,
            scores=np.full((n, score_columns(stage)), np.nan),
        )

    @property
    def label(self) -> str:
        return f"report {self.report_id}"

    @property
    def report(self) -> ReportSpec:
        return self.spec

    def robot_steps(self, n: int) -> int:
        """Robot-steps of a job of `n` trials."""
        return n * self.spec.steps

    def genomes_for(self, start: int, stop: int) -> np.ndarray:
        """Every trial runs the one controller."""
        return self.genome

    def implausible(self, rows: np.ndarray) -> str | None:
        """Why a result's rows cannot come from the report's trials
        (`evorobotics.reports.implausible`), or None."""
        return implausible(self.config, self.stage, self.spec, rows)

    def fill_scores(self, index: int, worker: str, scores: np.ndarray) -> Callable[[], None] | None:
        """Slot `index` is done: `worker`'s rows of it; once every slot is, what hands the
        report to its future (ValueError if it cannot be assembled)."""
        if not self._fill_scores(index, worker, scores) or self.scores is None:
            return None
        return partial(
            self.future.set_result, assemble(self.config, self.stage, self.spec, self.scores)
        )


@dataclass(kw_only=True)
class Rank(Asked):
    """A run's candidates ranked in one world, in flight (`evorobotics.evolution
    .rank_in_world`): the candidates cut into slots, scored into `scores` (validate's rows),
    ranked into `future` once all are. Its `config` is the `ranking_config`."""

    genomes: np.ndarray
    """(k, n_weights): the candidates, in their order."""
    future: Future[Ranked] = field(default_factory=Future)

    @classmethod
    def new(
        cls, config: RunConfig, world: World, genomes: np.ndarray, *, served: int, parts: int
    ) -> Rank:
        """`rank_in_world(config, genomes, world)` cut into about `parts` jobs, all pending.
        ValueError for a bad maze or candidates."""
        ranking = ranking_config(config, world)
        candidates = np.ascontiguousarray(genomes, dtype="<f8")
        weights = ranking.network_spec.weight_count
        if candidates.ndim != 2 or candidates.shape[1] != weights:
            raise ValueError(f"candidates of shape {candidates.shape} for a network of {weights}")
        if not 1 <= len(candidates) <= rank_candidates(ranking):
            raise ValueError(
                f"{len(candidates)} candidates to rank: 1 to {rank_candidates(ranking)}"
            )
        if not np.isfinite(candidates).all():
            raise ValueError("candidates contain NaN or infinity")
        _check_maze(ranking)
        n = len(candidates)
        slots = _stage_slots(n, parts)
        return cls(
            report_id=_digest("rank", ranking.model_dump_json(), candidates),
            config=ranking,
            genomes=candidates,
            slots=slots,
            pending=list(range(len(slots))),
            remaining=len(slots),
            served=served,
            stage="rank",
            scores=np.full((n, score_columns("rank")), np.nan),
        )

    @property
    def label(self) -> str:
        return f"ranking {self.report_id}"

    def robot_steps(self, n: int) -> int:
        """Robot-steps of a job of `n` candidates."""
        return stage_robot_steps(self.config, "rank", n)

    def genomes_for(self, start: int, stop: int) -> np.ndarray:
        return self.genomes[start:stop]

    def implausible(self, rows: np.ndarray) -> str | None:
        """Validate's rows: their bounds are checked as the result is decoded."""
        return None

    def fill_scores(self, index: int, worker: str, scores: np.ndarray) -> Callable[[], None] | None:
        """Slot `index` is done: `worker`'s rows of it; once every slot is, what hands the
        ranking (`ranked`, `rank_in_world`'s bit for bit) to its future."""
        if not self._fill_scores(index, worker, scores) or self.scores is None:
            return None
        return partial(self.future.set_result, ranked(Validated.from_scores(self.scores)))


AskedWork = Report | Rank
"""What the server asks for itself."""
Work = Run | Report | Rank
"""What the scheduler has in flight."""


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
