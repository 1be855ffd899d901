"""Reads and small writes of the store, keyword-only so call sites name what they pass.

The run loop's writes (generation commits) live in `server.runs.writer`; jobs in `server.runs.scheduler`.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from sqlalchemy import delete, func, select, update
from sqlalchemy.orm import Session

from evorobotics.evaluate import evaluate
from evorobotics.evolution import RunLoop, StrategyHistory, Told
from evorobotics.strategies import traits
from schemas.api import TERMINAL
from schemas.run import RunConfig
from schemas.wire import WireError, decode_frame
from server.core import integrity
from server.core.errors import BusyError, InvalidInputError, NotFoundError, ServerError
from server.core.models import Controller, Generation, Run, Study, utcnow
from server.runs import population
from server.runs.population import Population, Stored


def get_run(session: Session, *, run_id: int) -> Run | None:
    return session.get(Run, run_id)


def find_run(session: Session, *, run_id: int) -> Run:
    """The run, or NotFoundError (what the manager's changes and reads of one run want)."""
    run = get_run(session, run_id=run_id)
    if run is None:
        raise NotFoundError(f"no run with id {run_id}")
    return run


def list_runs(
    session: Session, *, statuses: Sequence[str] | None = None, limit: int = 100, offset: int = 0
) -> list[Run]:
    """Newest first."""
    if limit < 1 or offset < 0:
        raise ValueError(f"need limit >= 1 and offset >= 0, got {limit}, {offset}")
    query = select(Run).order_by(Run.id.desc()).limit(limit).offset(offset)
    if statuses is not None:
        query = query.where(Run.status.in_(list(statuses)))
    return list(session.scalars(query))


def count_runs_by_status(session: Session) -> dict[str, int]:
    rows = session.execute(select(Run.status, func.count()).group_by(Run.status))
    return {status: int(count) for status, count in rows}


def list_generations(session: Session, *, run_id: int) -> list[Generation]:
    query = select(Generation).where(Generation.run_id == run_id).order_by(Generation.generation)
    return list(session.scalars(query))


def best_so_far(session: Session, *, run_ids: Sequence[int]) -> dict[int, float]:
    """Run id -> the highest training fitness any of its committed generations' best reached
    (runs without a generation are left out)."""
    if not run_ids:
        return {}
    query = (
        select(Generation.run_id, func.max(Generation.best))
        .where(Generation.run_id.in_(list(run_ids)))
        .group_by(Generation.run_id)
    )
    return {int(run_id): float(best) for run_id, best in session.execute(query) if best is not None}


def champion_documents(session: Session, *, runs: Sequence[Run]) -> dict[int, str]:
    """Run id -> its champion's controller document (JSON) for the completed ones among `runs`."""
    shas = {run.id: run.champion_sha256 for run in runs if run.champion_sha256 is not None}
    if not shas:
        return {}
    query = select(Controller.sha256, Controller.document).where(
        Controller.sha256.in_(set(shas.values()))
    )
    found: dict[str, str] = {sha: document for sha, document in session.execute(query)}
    return {run_id: found[sha] for run_id, sha in shas.items() if sha in found}


def get_generation(session: Session, *, run_id: int, generation: int) -> Generation | None:
    return session.get(Generation, (run_id, generation))


def latest_generation(session: Session, *, run_id: int) -> Generation | None:
    query = (
        select(Generation)
        .where(Generation.run_id == run_id)
        .order_by(Generation.generation.desc())
        .limit(1)
    )
    return session.scalars(query).first()


def stored(session: Session, *, run_id: int, generations: Iterable[int]) -> dict[int, Stored]:
    """The stored frames of some committed generations, by generation number."""
    query = select(Generation.generation, Generation.population).where(
        Generation.run_id == run_id, Generation.generation.in_(list(generations))
    )
    found = {}
    for g, data in session.execute(query):
        try:
            found[g] = population.decode(
                integrity.unseal(data, f"run {run_id} generation {g} population")
            )
        except population.PopulationError as exc:
            raise ServerError(f"run {run_id} generation {g}: stored population: {exc}") from exc
    return found


def history(session: Session, *, run_id: int, generations: int) -> StrategyHistory:
    """What the run's loop was told in its first `generations` committed generations, in ask
    order: `RunLoop.resume` rebuilds a non-GA strategy from it (no evaluation)."""
    found = stored(session, run_id=run_id, generations=range(generations))
    missing = sorted(set(range(generations)) - found.keys())
    if missing:
        raise ServerError(f"run {run_id} lacks committed generations {missing[:5]} to resume")
    n = len(found[0].fitness) if generations else 0
    fitness = np.full((generations, n), np.nan)
    descriptors = np.full((generations, n, 4), np.nan)
    for g in range(generations):
        told = found[g]
        if told.fitness.shape != (n,):
            raise ServerError(f"run {run_id} generation {g} holds {told.fitness.shape} fitness")
        fitness[g] = told.fitness
        if told.descriptors is not None:
            descriptors[g] = told.descriptors
    return StrategyHistory(fitness, descriptors)


def replay(session: Session, *, run: Run, config: RunConfig, generation: int) -> RunLoop:
    """The run's loop at `generation` (its `ask` gives that generation's genomes), rebuilt
    without evaluating: from the nearest checkpoint before it (GA state and genomes), told
    the stored fitness of each generation since; a strategy that resumes from its history
    (pycma, pyribs objects) replays it from generation 0."""
    if generation > run.generation or generation >= config.generations:
        raise NotFoundError(f"run {run.id} has committed generations 0..{run.generation - 1} only")
    if generation == 0:
        return RunLoop(config)
    if not traits(config).in_state:
        return RunLoop.resume(config, history(session, run_id=run.id, generations=generation))
    where = f"run {run.id} generation"
    row = session.execute(
        select(Generation.generation, Generation.state, Generation.population)
        .where(
            Generation.run_id == run.id,
            Generation.generation < generation,
            Generation.state.is_not(None),
        )
        .order_by(Generation.generation.desc())
        .limit(1)
    ).first()
    loop = RunLoop(config)
    if row is not None:
        c, blob, frame = row
        assert blob is not None  # the query's condition
        try:
            checkpoint = population.decode(integrity.unseal(frame, f"{where} {c} population"))
            genomes = checkpoint.genomes
            if genomes is None:
                raise ServerError(f"{where} {c} has a GA state but no genomes")
            state = population.decode_state(
                integrity.unseal(blob, f"{where} {c} GA state"),
                ranked=genomes[population.by_rank(config, c, checkpoint.fitness, None).index],
            )
            if state.generation != c + 1:
                raise ValueError(f"a GA state of generation {state.generation}")
            loop = RunLoop(config, state)
        except (WireError, ValueError) as exc:
            raise ServerError(f"{where} {c}: stored checkpoint: {exc}") from exc
    told = stored(session, run_id=run.id, generations=range(loop.generation, generation))
    for g in range(loop.generation, generation):
        if g not in told:
            raise ServerError(f"run {run.id} lacks committed generation {g} to replay")
        try:
            loop.tell(told[g].fitness, None, told[g].descriptors)
        except ValueError as exc:
            raise ServerError(f"{where} {g}: stored fitness: {exc}") from exc
    return loop


def retold(session: Session, *, run: Run, config: RunConfig) -> tuple[RunLoop, Told]:
    """The loop of a run whose last generation is committed, and that generation as its loop
    was told it (replayed, then told the stored fitness, components and descriptors): what its
    champion is chosen from."""
    last = config.generations - 1
    loop = replay(session, run=run, config=config, generation=last)
    frame = stored(session, run_id=run.id, generations=[last]).get(last)
    if frame is None:
        raise ServerError(f"run {run.id} lacks committed generation {last}")
    try:
        return loop, loop.tell(frame.fitness, frame.components, frame.descriptors)
    except ValueError as exc:
        raise ServerError(f"run {run.id} generation {last}: stored fitness: {exc}") from exc


_REBUILDING = threading.Lock()
"""Held while a reader's generation is rebuilt (`ranked(exclusive=True)`): one at a time."""


def ranked(
    session: Session,
    *,
    run_id: int,
    generation: int,
    rank: int | None = None,
    components: bool = False,
    exclusive: bool = False,
) -> tuple[Population, np.ndarray]:
    """A committed generation by rank, fittest first, with its (n, weights) genomes in rank
    order; with `rank`, (1, weights) that rank's genome only (NotFoundError if the generation
    has no such rank). Between checkpoints the genomes are replayed (`replay`) and, with
    `components`, Eq 12's components simulated again: one generation's trials, the bits its
    workers reported. `exclusive` (a reader's request): BusyError while another such
    rebuild runs, so readers cannot make the server simulate on every core at once."""
    run = get_run(session, run_id=run_id)
    found = stored(session, run_id=run_id, generations=[generation]).get(generation)
    if run is None or found is None:
        raise NotFoundError(f"run {run_id} has no committed generation {generation}")
    n = len(found.fitness)
    if not n:
        raise NotFoundError(f"run {run_id} generation {generation} has no individuals")
    if rank is not None and not 0 <= rank < n:
        raise NotFoundError(
            f"run {run_id} generation {generation} has no individual of rank {rank}"
        )
    config = RunConfig.model_validate_json(run.config)
    asked, told = found.genomes, found.components
    if asked is None:
        if exclusive and not _REBUILDING.acquire(blocking=False):
            raise BusyError(
                f"run {run_id} generation {generation} is rebuilt from its checkpoint while "
                "another generation is: ask again"
            )
        try:
            asked = replay(session, run=run, config=config, generation=generation).ask()
            if components:
                told = evaluate(config, generation, asked).components
        finally:
            if exclusive:
                _REBUILDING.release()
    view = population.by_rank(config, generation, found.fitness, told)
    genomes = asked[view.index if rank is None else view.index[rank : rank + 1]]
    return view, genomes


def get_controller(session: Session, *, sha256: str) -> Controller | None:
    return session.get(Controller, sha256.lower())


SHA_PREFIX = re.compile(r"[0-9a-f]{8,64}")
"""A controller's sha256, or a prefix of at least 8 hex digits of it (tables show 12)."""


def find_controller(session: Session, *, sha256: str) -> Controller:
    """The controller whose sha256 is or starts with `sha256` (case-insensitive);
    InvalidInputError for a malformed or ambiguous prefix, NotFoundError for none."""
    prefix = sha256.lower()
    if SHA_PREFIX.fullmatch(prefix) is None:
        raise InvalidInputError(
            f"sha256 {sha256[:80]!r}: expected 8 to 64 hex digits (a sha256 or a prefix of it)"
        )
    if len(prefix) == 64:
        row = session.get(Controller, prefix)
        rows = [] if row is None else [row]
    else:
        query = select(Controller).where(Controller.sha256.startswith(prefix)).limit(2)
        rows = list(session.scalars(query))
    if not rows:
        raise NotFoundError(
            f"no controller with sha256 {prefix}" + ("" if len(prefix) == 64 else "...")
        )
    if len(rows) > 1:
        raise InvalidInputError(
            f"sha256 prefix {prefix} is ambiguous: several controllers start with it; give more digits"
        )
    return rows[0]


def champion(session: Session, *, run: Run) -> Controller | None:
    """A completed run's validated champion (`Run.champion_sha256`); None for any other run."""
    if run.champion_sha256 is None:
        return None
    row = get_controller(session, sha256=run.champion_sha256)
    if row is None:
        raise ServerError(f"run {run.id}: its champion {run.champion_sha256} is not stored")
    return row


def put_controller(
    session: Session,
    *,
    sha256: str,
    document: str,
    run_id: int | None,
    generation: int | None,
    fitness: float | None,
    replace: bool = False,
) -> Controller:
    """Store a document once; the same sha256 is the same controller, so a repeat is a no-op.

    With `replace`, a stored document of that sha256 takes this one's text and origin: a
    champion's document describes the same controller with more (its `validation`) than the
    rank's document a push may have stored before."""
    existing = session.get(Controller, sha256)
    if existing is not None:
        if replace:
            existing.document, existing.run_id = document, run_id
            existing.generation, existing.fitness = generation, fitness
        return existing
    row = Controller(
        sha256=sha256, document=document, run_id=run_id, generation=generation, fitness=fitness
    )
    session.add(row)
    return row


def get_study(session: Session, *, study_id: int) -> Study | None:
    return session.get(Study, study_id)


def list_studies(session: Session) -> list[Study]:
    """Newest first."""
    return list(session.scalars(select(Study).order_by(Study.id.desc())))


def study_runs(session: Session, *, study_id: int) -> list[Run]:
    """The study's runs in creation order (condition by condition, seed by seed)."""
    return list(session.scalars(select(Run).where(Run.study_id == study_id).order_by(Run.id)))


def study_status(statuses: Iterable[str]) -> str:
    """A study's status from its runs': running while any is unfinished, then failed if any
    failed, cancelled if any was cancelled, else completed."""
    found = set(statuses)
    if found - TERMINAL:
        return "running"
    for status in ("failed", "cancelled"):
        if status in found:
            return status
    return "completed"


def settle_study(session: Session, *, study_id: int | None) -> None:
    """Store the study's status derived from its runs' (called as one of them changes), and
    when it finished."""
    if study_id is None:
        return
    study = session.get(Study, study_id)
    if study is None:
        return
    statuses = session.scalars(select(Run.status).where(Run.study_id == study_id))
    status = study_status(statuses)
    if status != study.status:
        study.status = status
        study.finished_at = None if status == "running" else utcnow()


def delete_runs(session: Session, *, run_ids: Sequence[int]) -> None:
    """Delete runs and their generations; controllers stay, no longer naming them."""
    if not run_ids:
        return
    ids = list(run_ids)
    session.execute(delete(Generation).where(Generation.run_id.in_(ids)))
    session.execute(update(Controller).where(Controller.run_id.in_(ids)).values(run_id=None))
    session.execute(delete(Run).where(Run.id.in_(ids)))


@dataclass(frozen=True)
class StoreCheck:
    """What `check_store` read: rows verified against their checksums, rows stored before
    checksums (only decoded), and why each damaged row is."""

    generations: int
    generations_sealed: int
    traces: int
    traces_sealed: int
    damaged: list[str]


def check_store(session: Session) -> StoreCheck:
    """Read every generation (GA state, population) and trace batch, verify its checksum and
    decode it: `colony db check`."""
    from server.robots.store import TraceRow, check_trace

    damaged: list[str] = []
    generations = sealed_generations = 0
    query = select(
        Generation.run_id, Generation.generation, Generation.state, Generation.population
    )
    for run_id, g, state, frame in session.execute(query.execution_options(yield_per=64)):
        generations += 1
        sealed_generations += (state is None or integrity.sealed(state)) and integrity.sealed(frame)
        for what, blob in (("GA state", state), ("population", frame)):
            if blob is None:  # between checkpoints
                continue
            where = f"run {run_id} generation {g} {what}"
            try:
                data = integrity.unseal(blob, where)
                population.decode(data) if what == "population" else decode_frame(data)
            except integrity.DamagedRowError as exc:
                damaged.append(str(exc))
            except (WireError, population.PopulationError) as exc:
                damaged.append(f"{where}: cannot be decoded: {exc}")
    traces = sealed_traces = 0
    for row in session.scalars(select(TraceRow).execution_options(yield_per=256)):
        traces += 1
        sealed_traces += row.checksum is not None
        try:
            check_trace(row)
        except integrity.DamagedRowError as exc:
            damaged.append(str(exc))
    return StoreCheck(generations, sealed_generations, traces, sealed_traces, damaged)
