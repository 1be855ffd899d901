"""The run manager: lifecycle of runs and the generation loop over the job queue.

Each run composes the GA exactly as `evorobotics.evolution.evolve` does (ask with
`ga_rng(seed, g)`, fixed job slices, results concatenated in slice order, tell), so a server
run and `colony evolve` give the same populations bit for bit. The GA state after each `tell`
is committed with its generation; `ask` is a pure function of that state and the seed, so a
restarted server re-asks whatever generation was in flight and resumes exactly.

The hot path (one commit per generation) uses SQLAlchemy Core statements and per-run caches of
the parsed config, GA params, layout, latest GA state and where the last generation's genome
bytes are; lifecycle changes use the ORM. A generation is one row, its individuals one frame
(`server.population`). Eq 11 copies three quarters of each generation from the two before it:
a copy stores no bytes but the (generation, row) of the genome bytes it repeats. A
finished generation is told and the next asked in memory (`_advance`), and written by the job
queue afterwards (see `server.jobs`), so the zenoh dispatcher can send generation g + 1 before
g's transaction; lifecycle changes flush unwritten generations first.

Lifecycle: queued -> running <-> paused; queued/running/paused -> cancelled;
running -> completed | failed. Terminal: completed, failed, cancelled.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np
from sqlalchemy import Engine, Table, bindparam, func, insert, select, update
from sqlalchemy.orm import Session

from evorobotics.evolution import best_document
from evorobotics.ga import GAParams, GAState, TellMetrics, ask, ga_rng, init, lineage, tell
from evorobotics.layout import Layout, layout
from schemas.api import TERMINAL
from schemas.run import RunConfig
from schemas.wire import decode_frame, encode_frame
from server import crud, population
from server.db import session_factory
from server.errors import NotFoundError, TransitionError
from server.jobs import Advance, GenerationResults, JobQueue, RunOverError
from server.logs import context
from server.models import Generation, Run, utcnow
from server.population import Population
from server.settings import Settings

log = logging.getLogger(__name__)

_RUNS = cast(Table, Run.__table__)
_GENERATIONS = cast(Table, Generation.__table__)
"""The tables behind the hot path's Core statements."""
_ADVANCE_RUN = (
    update(_RUNS)
    .where(
        _RUNS.c.id == bindparam("run"),
        _RUNS.c.generation == bindparam("at"),
        _RUNS.c.status.in_(("running", "paused")),
    )
    .values(
        generation=bindparam("next"),
        best_fitness=bindparam("top"),
        evaluations=_RUNS.c.evaluations + bindparam("evaluated"),
    )
)
"""Moves a live run from generation `at` to `next` (built once: building it cost more than
executing it)."""
_INSERT_GENERATION = insert(_GENERATIONS)


def encode_state(state: GAState, *, with_ranked: bool = True) -> bytes:
    """GAState as a frame of raw arrays (schemas.wire: self-describing dtype and shape, no
    pickle; a tenth of the time of the .npz that servers before 0.2 wrote).

    The store passes `with_ranked=False`: `ranked` is the generation's genomes in rank order,
    already stored bit for bit in its population, so keeping it twice would double the bytes
    each commit writes.
    """
    return encode_frame({"kind": "ga-state"}, state.to_arrays(ranked=with_ranked))


def decode_state(data: bytes, *, ranked: Callable[[], np.ndarray] | None = None) -> GAState:
    """Inverse of `encode_state` (WireError on anything but its frame); `ranked` loads the
    population a compact encoding left out."""
    arrays = decode_frame(data)[1]
    if "ranked" not in arrays and "ranked_fitness" in arrays and ranked is not None:
        arrays["ranked"] = ranked()
    return GAState.from_arrays(arrays)


def stored_ranked(session: Session, *, run_id: int, generation: int) -> np.ndarray:
    """The committed generation's genomes in rank order (the GA state's `ranked`), a copy's
    bytes read from the generation that holds them."""
    return crud.ranked(session, run_id=run_id, generation=generation)[1]


@dataclass(frozen=True)
class _Plan:
    """What a run's config determines, parsed once per run instead of once per generation."""

    config: RunConfig
    params: GAParams
    layout: Layout


@dataclass(frozen=True)
class _Asked:
    """A generation asked inside a transaction, to hand to the queue once it has committed."""

    run_id: int
    config: RunConfig
    generation: int
    genomes: np.ndarray
    running: bool
    state: GAState
    """The GA state the generation's `tell` starts from."""


LOG_EVERY_S = 1.0
"""A run's "generation written" lines go out at INFO at most this often (and for its first and
last generation), the others at DEBUG: a span writes hundreds of generations a second."""


@dataclass(frozen=True)
class _Origins:
    """Where the genome bytes of a run's last written generation are, by rank: the (generation,
    row of that generation's `genomes`) holding them; -1 when unknown."""

    generation: int
    generations: np.ndarray
    """(n,) int64"""
    rows: np.ndarray
    """(n,) int64"""
    elite: tuple[int, int]
    """The same for rank 0 of `generation - 1` (the next generation's k-2 elite); (-1, -1)
    when there is none."""


_NO_ORIGIN = (-1, -1)


@dataclass(frozen=True)
class _Lineage:
    """`lineage` of a generation as the write uses it (the same for every generation >= 2)."""

    parents: np.ndarray
    """(n,) by index: the parent rank in the previous generation, -1 for none."""
    copies: np.ndarray
    """Indices of Eq 11's copies of the previous generation (elites and fill)."""
    copied: np.ndarray
    """Their parent ranks: each is a copy of that rank of the previous generation."""
    elite_k2: int
    """Index of the k-2 elite (a copy of rank 0 two generations back); -1 if none."""


@functools.lru_cache(maxsize=64)
def _lineage(params: GAParams, generation: int) -> _Lineage:
    kinds = lineage(params, generation)
    copies = [(i, p) for i, (kind, p) in enumerate(kinds) if kind in ("elite", "fill")]
    return _Lineage(
        parents=np.array([max(p, -1) for _, p in kinds], dtype=np.int64),
        copies=np.array([i for i, _ in copies], dtype=np.int64),
        copied=np.array([p for _, p in copies], dtype=np.int64),
        elite_k2=next((i for i, (kind, _) in enumerate(kinds) if kind == "elite_k2"), -1),
    )


def _read_origins(session: Session, run_id: int, generation: int, n: int) -> _Origins:
    """The origins of a written generation, from the store (one query; after a restart)."""
    found = crud.populations(session, run_id=run_id, generations=[generation - 1, generation])
    generations = np.full(n, -1, dtype=np.int64)
    rows = np.full(n, -1, dtype=np.int64)
    mine = found.get(generation)
    if mine is not None and len(mine) == n:
        generations[:], rows[:] = mine.genome_at[:, 0], mine.genome_at[:, 1]
    before = found.get(generation - 1)
    elite = (
        (int(before.genome_at[0, 0]), int(before.genome_at[0, 1]))
        if before is not None and len(before)
        else _NO_ORIGIN
    )
    return _Origins(generation, generations, rows, elite)


def _same_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(k,) whether row i of `a` and of `b` hold the same bytes (NaN payloads and -0.0 too)."""
    if a.shape != b.shape or a.dtype != b.dtype or a.ndim != 2:
        return np.zeros(len(a), dtype=bool)
    word = np.dtype(f"u{a.itemsize}") if a.itemsize in (1, 2, 4, 8) else np.dtype(np.uint8)
    bits_a = np.ascontiguousarray(a).view(word).reshape(len(a), -1)  # whole items at once
    bits_b = np.ascontiguousarray(b).view(word).reshape(len(b), -1)
    same: np.ndarray = (bits_a == bits_b).all(axis=1)
    return same


class RunManager:
    """Owns the store's writes: runs, generations and individuals; drives the job queue."""

    def __init__(self, engine: Engine, settings: Settings) -> None:
        self.settings = settings
        self.sessions = session_factory(engine)
        self._lock = threading.RLock()
        self.queue = JobQueue(
            self.sessions,
            lock=self._lock,
            lease_seconds=settings.lease_seconds,
            max_attempts=settings.max_attempts,
            on_generation_done=self._advance,
            on_run_failed=self._fail_id,
        )
        self.sessions.configure(info={"job_queue": self.queue})  # read by crud.job_counts
        self._plans: dict[int, _Plan] = {}
        self._states: dict[int, tuple[int, GAState]] = {}
        """run id -> (generation g, GA state after tell of g - 1): saves a decode per generation."""
        self._logged_at: dict[int, float] = {}
        """run id -> when a "generation written" line last went out at INFO (LOG_EVERY_S)."""
        self._origins: dict[int, _Origins] = {}
        """run id -> where the genome bytes of its last written generation are: saves a query
        per generation (see `_genome_origins`)."""
        self._stop = threading.Event()
        self._housekeeper: threading.Thread | None = None

    # lifecycle of the manager -------------------------------------------------------------

    def start(self) -> None:
        """Resume the runs of a previous life, then expire leases and promote queued runs."""
        self.recover()
        self._stop.clear()
        self._housekeeper = threading.Thread(
            target=self._housekeep, name="colony-housekeeper", daemon=True
        )
        self._housekeeper.start()

    def stop(self) -> None:
        """Stop housekeeping and write the generations told but not yet written (a restart
        would recompute them, bit for bit, but need not)."""
        self._stop.set()
        if self._housekeeper is not None:
            self._housekeeper.join(timeout=10.0)
            self._housekeeper = None
        with self._lock:
            try:
                self.queue.flush()
            except Exception as exc:
                log.warning("generations told but not written at shutdown: %s", exc)

    def _housekeep(self) -> None:
        while not self._stop.wait(self.settings.housekeeping_seconds):
            self.queue.expire(time.time())
            self.settle_write_failures()
            self.promote()

    def settle_write_failures(self) -> None:
        """Retry the writes the store refused; once they are in, pause the runs they stopped
        with the reason in `error`, so an operator sees it and resumes (nothing is lost)."""
        if not self.queue.stalled():  # told generations wait for the dispatcher's batch
            return
        with self._lock:
            if self.queue.unwritten():
                try:
                    self.queue.flush()
                except Exception as exc:
                    log.warning("store still refuses writes: %s", exc)
                    return
            failures = self.queue.write_failures()
            if not failures:
                return
            try:
                with self.sessions.begin() as session:
                    for run_id, message in failures.items():
                        run = session.get(Run, run_id)
                        if run is not None and run.status == "running":
                            run.status, run.error = "paused", message
                            context(log, run=run_id).warning(
                                "run %d paused after a refused write; resume it", run_id
                            )
            except Exception as exc:
                log.warning("could not pause the runs a refused write stopped: %s", exc)
                return
            self.queue.clear_write_failures(failures)

    def recover(self) -> None:
        """Re-ask the generation in flight of every live run (its results died with the process)."""
        asked: list[_Asked] = []
        with self._lock, self.sessions.begin() as session:
            runs = session.scalars(select(Run).where(Run.status.in_(("running", "paused"))))
            for run in runs:
                plan = self._plan(run)
                if run.generation >= plan.config.generations:
                    self._finish(session, run, plan.config)
                else:
                    asked.append(self._ask(session, run))
        self._hand_over(asked)
        self.promote()

    def _hand_over(self, asked: list[_Asked]) -> None:
        for a in asked:
            self.queue.add(
                run_id=a.run_id,
                config=a.config,
                generation=a.generation,
                genomes=a.genomes,
                running=a.running,
                state=a.state,
            )

    # run lifecycle ---------------------------------------------------------------------------

    def create_run(self, config: RunConfig) -> int:
        """Queue a run; it starts at once when fewer than `max_active_runs` are running."""
        with self._lock, self.sessions.begin() as session:
            run = Run(
                config=config.model_dump_json(),
                seed=config.seed,
                status="queued",
                generation=0,
                evaluations=0,
            )
            session.add(run)
            session.flush()
            run_id = run.id
        context(log, run=run_id).info(
            "run %d created: population %d, %d generations, seed %d",
            run_id,
            config.population,
            config.generations,
            config.seed,
        )
        self.promote()
        return run_id

    def promote(self) -> None:
        """Start queued runs, oldest first, up to `max_active_runs` running at once."""
        asked: list[_Asked] = []
        with self._lock:
            with self.sessions.begin() as session:
                running = session.scalar(
                    select(func.count()).select_from(Run).where(Run.status == "running")
                )
                free = self.settings.max_active_runs - int(running or 0)
                if free <= 0:
                    return
                queued = session.scalars(
                    select(Run).where(Run.status == "queued").order_by(Run.id).limit(free)
                )
                for run in queued:
                    try:
                        with session.begin_nested():
                            run.status = "running"
                            run.started_at = run.started_at or utcnow()
                            asked.append(self._ask(session, run))
                        context(log, run=run.id).info(
                            "run %d running from generation %d", run.id, run.generation
                        )
                    except (
                        Exception
                    ) as exc:  # a config the GA rejects fails its run, not the server
                        self._fail(session, run, f"cannot start: {exc}")
            self._hand_over(asked)

    def pause(self, run_id: int) -> None:
        with self._lock:
            self._transition(run_id, {"queued", "running"}, "paused")
            self.queue.set_running(run_id, False)
        context(log, run=run_id).info("run %d paused", run_id)

    def resume(self, run_id: int) -> None:
        with self._lock:
            with self.sessions.begin() as session:
                run = self._get(session, run_id)
                if run.status != "paused":
                    raise TransitionError(
                        f"run {run_id} is {run.status}; only a paused run resumes"
                    )
                run.status = "running" if run.started_at is not None else "queued"
                run.error = None  # e.g. a refused write that paused it
            self.queue.set_running(run_id, run.status == "running")
        context(log, run=run_id).info("run %d resumed (%s)", run_id, run.status)
        self.promote()

    def cancel(self, run_id: int) -> None:
        with self._lock:
            self.queue.flush()
            with self.sessions.begin() as session:
                run = self._get(session, run_id)
                if run.status in TERMINAL:
                    raise TransitionError(f"run {run_id} is already {run.status}")
                run.status, run.finished_at = "cancelled", utcnow()
            self._forget(run_id)
        context(log, run=run_id).info("run %d cancelled", run_id)
        self.promote()

    def fail_run(self, run_id: int, message: str) -> None:
        """Fail a run from outside a transaction (e.g. its generation could not be committed)."""
        with self._lock:
            self.queue.flush()
        with self._lock, self.sessions.begin() as session:
            run = session.get(Run, run_id)
            if run is not None and run.status not in TERMINAL:
                self._fail(session, run, message)
        self.promote()

    def _transition(self, run_id: int, allowed: set[str], target: str) -> None:
        with self._lock:
            self.queue.flush()
        with self._lock, self.sessions.begin() as session:
            run = self._get(session, run_id)
            if run.status not in allowed:
                raise TransitionError(
                    f"run {run_id} is {run.status}; cannot change to {target} "
                    f"(allowed from {', '.join(sorted(allowed))})"
                )
            run.status = target

    def _get(self, session: Session, run_id: int) -> Run:
        run = crud.get_run(session, run_id=run_id)
        if run is None:
            raise NotFoundError(f"no run with id {run_id}")
        return run

    def _forget(self, run_id: int) -> None:
        """Drop a run's jobs and caches (it is over)."""
        self.queue.forget(run_id)
        self._states.pop(run_id, None)
        self._origins.pop(run_id, None)
        self._logged_at.pop(run_id, None)
        self._plans.pop(run_id, None)

    # the generation loop ---------------------------------------------------------------------

    def _plan(self, run: Run) -> _Plan:
        plan = self._plans.get(run.id)
        if plan is None:
            config = RunConfig.model_validate_json(run.config)
            plan = _Plan(config, GAParams.from_config(config), layout(config.network_spec))
            self._plans[run.id] = plan
        return plan

    def _state_before(self, session: Session, run_id: int, plan: _Plan, g: int) -> GAState:
        """The GA state `ask`/`tell` of generation g start from."""
        cached = self._states.get(run_id)
        if cached is not None and cached[0] == g:
            return cached[1]
        if g == 0:
            return init(plan.layout, plan.params)
        previous = crud.get_generation(session, run_id=run_id, generation=g - 1)
        if previous is None:
            raise NotFoundError(f"run {run_id} has no committed generation {g - 1} to resume")
        state = decode_state(
            previous.state,
            ranked=lambda: stored_ranked(session, run_id=run_id, generation=g - 1),
        )
        self._states[run_id] = (g, state)
        return state

    def _ask(self, session: Session, run: Run) -> _Asked:
        """The genomes of generation `run.generation`, for the queue once the caller commits."""
        plan, g = self._plan(run), run.generation
        state = self._state_before(session, run.id, plan, g)
        genomes, _ = ask(ga_rng(plan.config.seed, g), state, plan.params, plan.layout)
        return _Asked(run.id, plan.config, g, genomes, run.status == "running", state)

    def _advance(self, results: GenerationResults) -> Advance:
        """Tell the GA and ask the next generation in memory; the write stores the generation
        whole (in the queue's one transaction) and finishes the run after its last one."""
        run_id, g = results.run_id, results.generation
        plan = self._plans.get(run_id)
        cached = self._states.get(run_id)
        if plan is not None and cached is not None and cached[0] == g:
            before = cached[1]
        else:  # a cold cache (after a restart): read the run and its last state
            with self.sessions() as session:
                if plan is None:
                    plan = self._plan(self._get(session, run_id))
                before = self._state_before(session, run_id, plan, g)
        state, metrics = tell(results.genomes, results.fitness, before, plan.params)
        self._states[run_id] = (g + 1, state)
        last = g + 1 >= plan.config.generations
        following = None
        if not last:
            following, _ = ask(ga_rng(plan.config.seed, g + 1), state, plan.params, plan.layout)

        def write(session: Session) -> None:
            self._write_generation(session, results, plan, before, state, metrics)
            if last:
                self._finish(session, self._get(session, run_id), plan.config)

        return Advance(following, state, write)

    def _write_generation(
        self,
        session: Session,
        results: GenerationResults,
        plan: _Plan,
        before: GAState,
        state: GAState,
        metrics: TellMetrics,
    ) -> None:
        """Store generation g (statistics, GA state, its population as one frame) and move
        the run to g + 1.

        `before` is the state g was asked from (`tell` of g starts from it). A copy's genome
        bytes are stored once, at its origin (see `_genome_at`).
        """
        run_id, g = results.run_id, results.generation
        genomes, fitness, components = results.genomes, results.fitness, results.components
        order = metrics.order
        top = float(fitness[order[0]])
        conn = session.connection()  # Core on the session's transaction: no ORM unit of work
        moved = conn.execute(
            _ADVANCE_RUN,
            {
                "run": run_id,
                "at": g,
                "next": g + 1,
                "top": top if np.isfinite(top) else None,
                "evaluated": plan.config.population,
            },
        )
        if moved.rowcount != 1:
            raise RunOverError(f"run {run_id} is not live at generation {g}; nothing written")
        kin = _lineage(plan.params, min(g, 2))  # every generation from 2 on has the same
        genome_at = self._genome_at(session, run_id, g, kin, genomes, before, order)
        ranked = Population(
            index=order,
            parent=kin.parents[order],
            fitness=fitness[order],
            components=components[order],
            genome_at=genome_at,
            genomes=genomes[order[genome_at[:, 0] == g]],
        )
        conn.execute(
            _INSERT_GENERATION,
            {
                "run_id": run_id,
                "generation": g,
                "best": metrics.best,
                "mean": metrics.mean,
                "worst": metrics.worst,
                "nan_count": metrics.nan_count,
                "state": encode_state(state, with_ranked=False),
                "population": population.encode(ranked),
                "committed_at": utcnow(),
            },
        )
        now = time.monotonic()
        loud = g == 0 or g + 1 >= plan.config.generations
        if loud or now - self._logged_at.get(run_id, -math.inf) >= LOG_EVERY_S:
            self._logged_at[run_id] = now
            level = logging.INFO
        else:
            level = logging.DEBUG
        context(log, run=run_id).log(
            level,
            "run %d generation %d written: best %.4g, mean %.4g",
            run_id,
            g,
            metrics.best,
            metrics.mean,
        )

    def _genome_at(
        self,
        session: Session,
        run_id: int,
        g: int,
        kin: _Lineage,
        genomes: np.ndarray,
        before: GAState,
        order: np.ndarray,
    ) -> np.ndarray:
        """(n, 2) by rank: the (generation, row of its `genomes`) holding each individual's
        genome bytes. Generation 0, mutants, and anything whose bytes differ from its origin's
        store their own, at (g, k) for the k-th of them in rank order.

        Eq 11 copies genomes: an elite or fill of parent rank p is rank p of g - 1
        (`before.ranked[p]`), the k-2 elite rank 0 of g - 2 (`before.elite_k2`). Their origins
        are remembered per run (`_origins`, read back with one query after a restart) and
        followed one hop, so an origin always holds bytes. Records g's origins for g + 1.
        """
        n = len(genomes)
        origin_g = np.full(n, -1, dtype=np.int64)
        origin_r = np.full(n, -1, dtype=np.int64)
        previous: _Origins | None = None
        if g >= 1 and before.ranked is not None and before.ranked.shape == genomes.shape:
            previous = self._origins.get(run_id)
            if previous is None or previous.generation != g - 1:
                previous = _read_origins(session, run_id, g - 1, n)
            at_g, at_r = previous.generations[kin.copied], previous.rows[kin.copied]
            same = _same_rows(genomes[kin.copies], before.ranked[kin.copied]) & (at_g >= 0)
            origin_g[kin.copies[same]], origin_r[kin.copies[same]] = at_g[same], at_r[same]
            k2 = kin.elite_k2
            if (
                k2 >= 0
                and before.elite_k2 is not None
                and previous.elite[0] >= 0
                and _same_rows(genomes[k2 : k2 + 1], before.elite_k2[np.newaxis, :])[0]
            ):
                origin_g[k2], origin_r[k2] = previous.elite
        at = np.stack([origin_g[order], origin_r[order]], axis=1)
        own = at[:, 0] < 0
        at[own, 0], at[own, 1] = g, np.arange(int(own.sum()))
        self._origins[run_id] = _Origins(
            generation=g,
            generations=at[:, 0],
            rows=at[:, 1],
            elite=_NO_ORIGIN
            if previous is None
            else (int(previous.generations[0]), int(previous.rows[0])),
        )
        return at

    def _finish(self, session: Session, run: Run, config: RunConfig) -> None:
        run.status, run.finished_at = "completed", utcnow()
        sha = self.store_best(session, run, config)
        self._forget(run.id)
        context(log, run=run.id).info("run %d completed; best controller %s", run.id, sha)

    def _fail(self, session: Session, run: Run, message: str) -> None:
        run.status, run.error, run.finished_at = "failed", message, utcnow()
        self._forget(run.id)
        context(log, run=run.id).error("run %d failed: %s", run.id, message)

    def _fail_id(self, session: Session, run_id: int, message: str) -> None:
        run = session.get(Run, run_id)
        if run is not None and run.status not in TERMINAL:
            self._fail(session, run, message)

    # results -----------------------------------------------------------------------------------

    def store_best(self, session: Session, run: Run, config: RunConfig) -> str | None:
        """Store the best controller so far (rank 0 of the latest generation); its sha256."""
        latest = crud.latest_generation(session, run_id=run.id)
        if latest is None:
            return None
        found, genomes = crud.ranked(session, run_id=run.id, generation=latest.generation, rank=0)
        document = best_document(
            config,
            genomes,
            found.fitness[:1],
            np.array([0]),
            generation=latest.generation,
            run=run.id,
        )
        crud.put_controller(
            session,
            sha256=document.sha256,
            document=document.to_json(),
            run_id=run.id,
            generation=latest.generation,
            fitness=document.fitness,
        )
        return document.sha256

    def best(self, run_id: int) -> str:
        """sha256 of the run's best controller so far (stored); NotFoundError before gen 0."""
        with self._lock:
            self.queue.flush()
        with self._lock, self.sessions.begin() as session:
            run = self._get(session, run_id)
            sha = self.store_best(session, run, RunConfig.model_validate_json(run.config))
        if sha is None:
            raise NotFoundError(f"run {run_id} has no completed generation yet")
        return sha
