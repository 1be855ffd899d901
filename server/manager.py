"""The run manager: lifecycle of runs and the generation loop over the job queue.

Each run composes the GA exactly as `evorobotics.evolution.evolve` does (ask with
`ga_rng(seed, g)`, fixed job slices, results concatenated in slice order, tell), so a server
run and `colony evolve` give the same populations bit for bit. The GA state after each `tell`
is committed with its generation; `ask` is a pure function of that state and the seed, so a
restarted server re-asks whatever generation was in flight and resumes exactly.

Lifecycle: queued -> running <-> paused; queued/running/paused -> cancelled;
running -> completed | failed. Terminal: completed, failed, cancelled.
"""

from __future__ import annotations

import io
import threading
import time

import numpy as np
from sqlalchemy import Engine, delete, func, insert, select
from sqlalchemy.orm import Session

from evorobotics.evolution import best_document
from evorobotics.ga import GAParams, GAState, ask, ga_rng, init, lineage, tell
from evorobotics.layout import layout
from schemas.api import TERMINAL
from schemas.run import RunConfig
from server import crud
from server.db import session_factory
from server.errors import NotFoundError, TransitionError
from server.jobs import JobQueue
from server.models import Generation, Individual, Job, Run, pack, utcnow
from server.settings import Settings


def encode_state(state: GAState) -> bytes:
    """GAState as an uncompressed .npz (self-describing dtype and shape, no pickle)."""
    buffer = io.BytesIO()
    np.savez(buffer, allow_pickle=False, **state.to_arrays())
    return buffer.getvalue()


def decode_state(data: bytes) -> GAState:
    with np.load(io.BytesIO(data), allow_pickle=False) as arrays:
        return GAState.from_arrays({name: arrays[name] for name in arrays.files})


class RunManager:
    """Owns the store's writes: runs, generations, individuals and the job queue."""

    def __init__(self, engine: Engine, settings: Settings) -> None:
        self.settings = settings
        self.sessions = session_factory(engine)
        self._lock = threading.RLock()
        self.queue = JobQueue(
            self.sessions,
            lock=self._lock,
            lease_seconds=settings.lease_seconds,
            max_attempts=settings.max_attempts,
            on_generation_done=self._commit_generation,
            on_run_failed=self._fail,
        )
        self._states: dict[int, tuple[int, GAState]] = {}
        """run id -> (generation g, GA state after tell of g - 1): saves a decode per generation."""
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
        self._stop.set()
        if self._housekeeper is not None:
            self._housekeeper.join(timeout=10.0)
            self._housekeeper = None

    def _housekeep(self) -> None:
        while not self._stop.wait(self.settings.housekeeping_seconds):
            self.queue.expire(time.time())
            self.promote()

    def recover(self) -> None:
        """Release old leases and make sure every live run has the jobs of its next generation."""
        self.queue.release_all()
        with self._lock, self.sessions.begin() as session:
            runs = session.scalars(select(Run).where(Run.status.in_(("running", "paused"))))
            for run in runs:
                config = RunConfig.model_validate_json(run.config)
                if run.generation >= config.generations:
                    self._finish(session, run, config)
                    continue
                jobs = session.execute(
                    select(func.count(), func.coalesce(func.sum(Job.status != "done"), 0)).where(
                        Job.run_id == run.id, Job.generation == run.generation
                    )
                ).one()
                if jobs[0] == 0:
                    self._ask(session, run, config)
                elif jobs[1] == 0:
                    self._commit_generation(session, run, run.generation)
        self.promote()

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
                served=0,
            )
            session.add(run)
            session.flush()
            run_id = run.id
        self.promote()
        return run_id

    def promote(self) -> None:
        """Start queued runs, oldest first, up to `max_active_runs` running at once."""
        with self._lock, self.sessions.begin() as session:
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
                        config = RunConfig.model_validate_json(run.config)
                        run.status = "running"
                        run.started_at = run.started_at or utcnow()
                        self._ask(session, run, config)
                except Exception as exc:  # a config the GA rejects fails its run, not the server
                    self._fail(session, run, f"cannot start: {exc}")

    def pause(self, run_id: int) -> None:
        self._transition(run_id, {"queued", "running"}, "paused")

    def resume(self, run_id: int) -> None:
        with self._lock, self.sessions.begin() as session:
            run = self._get(session, run_id)
            if run.status != "paused":
                raise TransitionError(f"run {run_id} is {run.status}; only a paused run resumes")
            run.status = "running" if run.started_at is not None else "queued"
        self.queue.work_available.set()
        self.promote()

    def cancel(self, run_id: int) -> None:
        with self._lock, self.sessions.begin() as session:
            run = self._get(session, run_id)
            if run.status in TERMINAL:
                raise TransitionError(f"run {run_id} is already {run.status}")
            run.status, run.finished_at = "cancelled", utcnow()
            session.execute(delete(Job).where(Job.run_id == run_id))
        self._forget(run_id)
        self.promote()

    def fail_run(self, run_id: int, message: str) -> None:
        """Fail a run from outside a transaction (e.g. its generation could not be committed)."""
        with self._lock, self.sessions.begin() as session:
            run = session.get(Run, run_id)
            if run is not None and run.status not in TERMINAL:
                self._fail(session, run, message)
        self.promote()

    def _transition(self, run_id: int, allowed: set[str], target: str) -> None:
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
        self._states.pop(run_id, None)
        self.queue.forget(run_id)

    # the generation loop ---------------------------------------------------------------------

    def _state_before(self, session: Session, run: Run, config: RunConfig, g: int) -> GAState:
        """The GA state `ask`/`tell` of generation g start from."""
        cached = self._states.get(run.id)
        if cached is not None and cached[0] == g:
            return cached[1]
        if g == 0:
            return init(layout(config.network_spec), GAParams.from_config(config))
        previous = crud.get_generation(session, run_id=run.id, generation=g - 1)
        if previous is None:
            raise NotFoundError(f"run {run.id} has no committed generation {g - 1} to resume")
        return decode_state(previous.state)

    def _ask(self, session: Session, run: Run, config: RunConfig) -> None:
        """Create the jobs of generation `run.generation`."""
        g = run.generation
        state = self._state_before(session, run, config, g)
        lay = layout(config.network_spec)
        genomes, _ = ask(ga_rng(config.seed, g), state, GAParams.from_config(config), lay)
        self.queue.add(session, run=run, generation=g, genomes=genomes)

    def _commit_generation(self, session: Session, run: Run, g: int) -> None:
        """Tell the GA, store the generation whole, then ask the next (one transaction)."""
        config = RunConfig.model_validate_json(run.config)
        params = GAParams.from_config(config)
        genomes, fitness, components = self.queue.results(session, run_id=run.id, generation=g)
        state, metrics = tell(genomes, fitness, self._state_before(session, run, config, g), params)
        order = metrics.order
        parents = lineage(params, g)
        session.add(
            Generation(
                run_id=run.id,
                generation=g,
                best=metrics.best,
                mean=metrics.mean,
                worst=metrics.worst,
                nan_count=metrics.nan_count,
                state=encode_state(state),
                committed_at=utcnow(),
            )
        )
        _, dtype, shape = pack(genomes[0])
        session.execute(
            insert(Individual),
            [
                {
                    "run_id": run.id,
                    "generation": g,
                    "rank": r,
                    "index": int(i),
                    "parent": parents[i][1] if parents[i][1] >= 0 else None,
                    "fitness": float(fitness[i]),
                    "components": components[i].tobytes(),
                    "genome": genomes[i].tobytes(),
                    "dtype": dtype,
                    "shape": shape,
                }
                for r, i in enumerate(order)
            ],
        )
        session.execute(delete(Job).where(Job.run_id == run.id, Job.generation == g))
        top = float(fitness[order[0]])
        run.best_fitness = top if np.isfinite(top) else None
        run.generation = g + 1
        self._states[run.id] = (g + 1, state)
        if run.generation >= config.generations:
            self._finish(session, run, config)
        else:
            self._ask(session, run, config)

    def _finish(self, session: Session, run: Run, config: RunConfig) -> None:
        run.status, run.finished_at = "completed", utcnow()
        self.store_best(session, run, config)
        self._forget(run.id)

    def _fail(self, session: Session, run: Run, message: str) -> None:
        run.status, run.error, run.finished_at = "failed", message, utcnow()
        session.execute(delete(Job).where(Job.run_id == run.id))
        self._forget(run.id)

    # results -----------------------------------------------------------------------------------

    def store_best(self, session: Session, run: Run, config: RunConfig) -> str | None:
        """Store the best controller so far (rank 0 of the latest generation); its sha256."""
        latest = crud.latest_generation(session, run_id=run.id)
        if latest is None:
            return None
        top = crud.get_individual(session, run_id=run.id, generation=latest.generation, rank=0)
        if top is None:
            raise NotFoundError(f"run {run.id} generation {latest.generation} has no rank 0")
        genome = np.frombuffer(top.genome, dtype=np.dtype(top.dtype))
        document = best_document(
            config,
            genome[np.newaxis, :],
            np.array([top.fitness]),
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
        with self._lock, self.sessions.begin() as session:
            run = self._get(session, run_id)
            sha = self.store_best(session, run, RunConfig.model_validate_json(run.config))
        if sha is None:
            raise NotFoundError(f"run {run_id} has no completed generation yet")
        return sha
