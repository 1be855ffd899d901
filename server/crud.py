"""Reads and small writes of the store, keyword-only so call sites name what they pass.

The run loop's writes (generation commits) live in `server.manager`; jobs in `server.jobs`.
"""

from __future__ import annotations

from collections.abc import Sequence

from sqlalchemy import and_, func, outerjoin, select
from sqlalchemy.orm import Session, aliased, defer

from server.errors import ServerError
from server.jobs import JobQueue
from server.models import Controller, Generation, Individual, Robot, Run, Worker

_ORIGIN = aliased(Individual, name="origin")
WITH_ORIGIN = outerjoin(
    Individual,
    _ORIGIN,
    and_(
        _ORIGIN.run_id == Individual.run_id,
        _ORIGIN.generation == Individual.origin_generation,
        _ORIGIN.rank == Individual.origin_rank,
    ),
)
"""`individuals` LEFT JOIN the row holding a copy's genome bytes (select from it with GENOME)."""
GENOME = func.coalesce(Individual.genome, _ORIGIN.genome)
"""An individual's genome bytes: its own, or a copy's origin's (one hop: origins hold bytes)."""


def get_run(session: Session, *, run_id: int) -> Run | None:
    return session.get(Run, run_id)


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


def list_individuals(session: Session, *, run_id: int, generation: int) -> list[Individual]:
    """Ranked, fittest first."""
    query = (
        select(Individual)
        .where(Individual.run_id == run_id, Individual.generation == generation)
        .order_by(Individual.rank)
    )
    return list(session.scalars(query))


def individuals_with_genomes(
    session: Session, *, run_id: int, generation: int, rank: int | None = None
) -> list[tuple[Individual, bytes]]:
    """Ranked, fittest first (only `rank` if given), each with its genome bytes: read them
    here, not from `Individual.genome`, which is NULL for a copy."""
    query = (
        select(Individual, GENOME)
        .select_from(WITH_ORIGIN)
        .options(defer(Individual.genome, raiseload=True))
        .where(Individual.run_id == run_id, Individual.generation == generation)
        .order_by(Individual.rank)
    )
    if rank is not None:
        query = query.where(Individual.rank == rank)
    out = []
    for row, genome in session.execute(query):
        if genome is None:
            raise ServerError(
                f"run {run_id} generation {generation} rank {row.rank}: no genome bytes at its "
                f"origin ({row.origin_generation}, {row.origin_rank})"
            )
        out.append((row, bytes(genome)))
    return out


def get_controller(session: Session, *, sha256: str) -> Controller | None:
    return session.get(Controller, sha256.lower())


def put_controller(
    session: Session,
    *,
    sha256: str,
    document: str,
    run_id: int | None,
    generation: int | None,
    fitness: float | None,
) -> Controller:
    """Store a document once; the same sha256 is the same document, so a repeat is a no-op."""
    existing = session.get(Controller, sha256)
    if existing is not None:
        return existing
    row = Controller(
        sha256=sha256, document=document, run_id=run_id, generation=generation, fitness=fitness
    )
    session.add(row)
    return row


def job_counts(session: Session) -> dict[str, int]:
    """Jobs of the generations in flight by status (pending, leased, done).

    Jobs live in the run manager's memory (`server.jobs.JobQueue`), not in a table; the
    manager's sessions carry its queue as `session.info["job_queue"]`. A session without one
    (e.g. a read-only tool on the database file) sees no jobs.
    """
    queue = session.info.get("job_queue")
    if isinstance(queue, JobQueue):
        return queue.counts()
    return {"pending": 0, "leased": 0, "done": 0}


def list_workers(session: Session) -> list[Worker]:
    return list(session.scalars(select(Worker).order_by(Worker.id)))


def list_robots(session: Session) -> list[Robot]:
    return list(session.scalars(select(Robot).order_by(Robot.id)))
