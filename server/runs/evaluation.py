"""The server's own evaluations and its checks of a worker's result: a job (`run_job`: the
in-process executors' and the referee's, a generation's, a champion's stage's or a report's), a
spot-check (`spot_check`, `spot_check_scores` for a stage's or a report's: re-evaluate some of
a result here; `cross_check`: a generation's jobs against each other, judged here only when
they differ), a span's
digest (`digest_error`: the genomes it evaluated were those asked) and a stored claim before
it is served (`repeats_claim`).

Runs are deterministic, so a spot-check compares bit for bit; it draws the individuals with
`secrets`, never the run's seed stream, so a worker cannot predict them.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable, Sequence

import numpy as np

from evorobotics.evaluate import evaluate, implausible, robot_steps
from evorobotics.evolution import RunLoop
from evorobotics.reports import implausible as implausible_rows
from evorobotics.reports import stage_scores, stage_steps
from schemas.run import RunConfig
from schemas.wire import Job, Result, genome_digest
from server.runs.jobs import Lease, Run, Work
from server.runs.workers import credential

_CHOOSE = secrets.SystemRandom()
"""Picks the individuals to re-evaluate: a worker cannot predict them from the run's seed."""


def run_job(job: Job, worker: str) -> Result:
    """Evaluate `job` (one generation of its slice) as a Result; an error, or an evaluation
    the scheduler would refuse as implausible (`implausible`), becomes one: this process's
    own evaluation failing fails the run, it quarantines nobody."""
    began = time.perf_counter()
    try:
        if job.key.stage != "train":
            return _run_stage(job, worker, began)
        genomes = job.evaluated()
        evaluation = evaluate(job.config, job.key.generation, genomes)
        why = implausible(
            job.config, evaluation.fitness, evaluation.components, evaluation.descriptors
        )
        if why is not None:
            raise ValueError(f"the evaluation is implausible: {why}")
        seconds = time.perf_counter() - began
        return Result(
            key=job.key,
            worker=worker,
            start=job.start,
            stop=job.stop,
            robot_steps_per_s=(
                robot_steps(job.config, len(genomes)) / seconds if seconds > 0 else 0.0
            ),
            seconds=seconds,
            checks=len(genomes) - (job.stop - job.start),
            fitness=evaluation.fitness[None],
            components=evaluation.components[None],
            descriptors=evaluation.descriptors[None],
        )
    except Exception as exc:  # an evaluation error is the run's problem, not the thread's
        return Result(
            key=job.key,
            worker=worker,
            start=job.start,
            stop=job.stop,
            error=f"{type(exc).__name__}: {exc}",
        )


def _run_stage(job: Job, worker: str, began: float) -> Result:
    """A champion stage's or a report's job: its rows' scores (`stage_scores`); rows the
    scheduler would refuse as implausible are an error."""
    stage, report = job.key.stage, job.report
    scores = stage_scores(job.config, stage, job.genomes, job.start, job.stop, report)
    why = None if report is None else implausible_rows(job.config, stage, report, scores)
    if why is not None:
        raise ValueError(f"the report's rows are implausible: {why}")
    seconds = time.perf_counter() - began
    steps = stage_steps(job.config, stage, job.stop - job.start, report)
    return Result(
        key=job.key,
        worker=worker,
        start=job.start,
        stop=job.stop,
        robot_steps_per_s=steps / seconds if seconds > 0 else 0.0,
        seconds=seconds,
        scores=scores,
    )


def spot_check_scores(
    result: Result, lease: Lease | None, work: Work | None, *, wanted: int, totals: dict[str, int]
) -> str | None:
    """`spot_check` of a champion stage's or a report's result: `wanted` of its rows
    (candidates, test poses or a report's trials, drawn with `secrets`) scored again here, bit
    for bit."""
    scores = result.scores
    if (
        wanted == 0
        or scores is None
        or lease is None
        or work is None
        or work.scores is None
        or lease.worker != result.worker
        or (result.start, result.stop) != (lease.start, lease.stop)
    ):
        return None
    config, stage, report = work.config, work.stage, work.report
    totals["results_checked"] += 1
    n = lease.stop - lease.start
    for row in sorted(_CHOOSE.sample(range(n), min(wanted, n))):
        i = lease.start + row
        again = stage_scores(config, stage, work.genomes_for(i, i + 1), i, i + 1, report)[0]
        totals["individuals_checked"] += 1
        totals["robot_steps_checked"] += work.robot_steps(1)
        if not _same_bits(scores[row], again):
            return (
                f"worker {result.worker} {work.label} {stage} row {i}: claimed scores "
                f"{scores[row].tolist()!r}, recomputed {again.tolist()!r}"
            )
    return None


def implausible_claims(result: Result, work: Work | None) -> str | None:
    """Why a generation of `result` claims what its run's trials cannot produce
    (`implausible`), naming worker, run and generation; None if none does, or it carries no
    evaluation or its work is not in flight. A report's or a ranking's rows: by its own
    `implausible`. Judged before any lease or spot-check, so a forgery counts against its
    credential even when it comes late. A report's or ranking's result keyed to another stage
    than its own is no job of it (no lease either): its rows are not read."""
    if work is None:
        return None
    if not isinstance(work, Run):
        if work.stage != result.key.stage:
            return None
        why = None if result.scores is None else work.implausible(result.scores)
        return None if why is None else f"worker {result.worker} {work.label}: {why}"
    fitness, components, descriptors = result.fitness, result.components, result.descriptors
    if fitness is None or components is None or descriptors is None:
        return None
    config = work.loop.config
    every = implausible(  # each check is per individual: all generations in one call
        config,
        fitness.reshape(-1),
        components.reshape(-1, *components.shape[2:]),
        descriptors.reshape(-1, descriptors.shape[-1]),
    )
    if every is None:
        return None
    for i in range(result.generations):  # which generation, named as a worker sees it
        why = implausible(config, fitness[i], components[i], descriptors[i])
        if why is not None:
            return (
                f"worker {result.worker} run {result.key.run_id} generation "
                f"{result.key.generation + i}: {why}"
            )
    return None


def spot_check(
    result: Result,
    lease: Lease | None,
    run: Run | None,
    *,
    wanted: int,
    job_size: Callable[[RunConfig, int, int | None], int],
    totals: dict[str, int],
) -> str | None:
    """Re-evaluate `wanted` individuals of `result`, drawn with `secrets` among the generations
    it may complete (those of `lease` that `job_size` leaves whole); why it fails (worker, run,
    generation, individual, claimed and recomputed), or None (it passed, or it counts for
    nothing anyway). Counts into `totals` (`Scheduler.spot_totals`)."""
    fitness, components, descriptors = result.fitness, result.components, result.descriptors
    if (
        wanted == 0
        or fitness is None
        or components is None
        or descriptors is None
        or lease is None
        or run is None
        or lease.worker != result.worker
        or (result.start, result.stop) != (lease.start, lease.stop)
    ):
        return None  # off, an error, or dropped by `Scheduler.settle`
    n = lease.stop - lease.start
    loop = run.loop
    config = loop.config
    generations = 1  # then those `Ledger._complete` will move the span's lease on to
    while (
        generations < min(result.generations, lease.span_left + 1)
        and run.running
        and job_size(config, loop.generation + generations, run.run_id) >= config.population
    ):
        generations += 1
    picks = sorted(_CHOOSE.sample(range(generations * n), min(wanted, generations * n)))
    asked, shadow = loop.ask(), None
    totals["results_checked"] += 1
    for i in range(picks[-1] // n + 1):
        if i > 0:  # a span's later generation: the genomes its claimed fitness leads to
            shadow = shadow or loop.fork()  # the run's loop then takes its steps for free
            shadow.tell(fitness[i - 1], components[i - 1], descriptors[i - 1])
            asked = shadow.ask()
        rows = [p % n for p in picks if p // n == i]
        if not rows:
            continue
        generation = loop.generation + i
        again = evaluate(config, generation, asked[lease.start + np.array(rows)])
        totals["individuals_checked"] += len(rows)
        totals["robot_steps_checked"] += robot_steps(config, len(rows))
        claimed = (fitness[i, rows], components[i, rows], descriptors[i, rows])
        recomputed = (again.fitness, again.components, again.descriptors)
        where = lease.start + np.array(rows)
        why = _mismatch(result.worker, run.run_id, generation, where, claimed, recomputed)
        if why is not None:
            return why
    return None


def cross_check(
    run: Run, *, trusted: Callable[[str], bool], totals: dict[str, int]
) -> list[tuple[str, str]]:
    """Each slot's `check_rows` of a complete generation, as its worker claimed them, against
    the next slot's worker's evaluation of them (`Run.checked`): the workers that lied, each
    with why. A mismatch is judged by this process's own evaluation; so is a slot whose
    claimer's credential knew which rows are checked (it checked them, or was ever leased the
    job that checks them: `Run.shown`), on others drawn afresh. Slots of this process's own
    evaluators (`trusted`) are not checked."""
    config, generation, genomes = run.config, run.generation, run.loop.ask()
    liars: list[tuple[str, str]] = []
    for j, rows in enumerate(run.check_rows):
        claimer, entry = run.slots[j].worker, run.checked.get(j)
        if claimer is None or entry is None or trusted(claimer):
            continue
        checker, *theirs = entry
        if credential(claimer) in run.shown.get(j, set()) | {credential(checker)}:
            slot = run.slots[j]
            unseen = sorted(set(range(slot.start, slot.stop)) - set(rows.tolist()))
            pool = unseen if len(unseen) >= len(rows) else range(slot.start, slot.stop)
            rows = np.array(sorted(_CHOOSE.sample(pool, len(rows))))
            theirs = []
        totals["results_checked"] += 1
        totals["individuals_checked"] += len(rows)
        totals["robot_steps_checked"] += robot_steps(config, len(rows))
        claimed = (run.fitness[rows], run.components[rows], run.descriptors[rows])
        if theirs and all(_same_bits(a, b) for a, b in zip(claimed, theirs, strict=True)):
            continue
        again = evaluate(config, generation, genomes[rows])
        recomputed = (again.fitness, again.components, again.descriptors)
        for who, said in ((claimer, claimed), (checker, tuple(theirs))):
            why = (
                None if not said else _mismatch(who, run.run_id, generation, rows, said, recomputed)
            )
            if why is not None and not trusted(who):
                liars.append((who, why))
    return liars


def _mismatch(
    worker: str,
    run_id: int,
    generation: int,
    rows: np.ndarray,
    claimed: tuple[np.ndarray, ...],
    recomputed: tuple[np.ndarray, ...],
) -> str | None:
    """Why `worker`'s claimed fitness, components and descriptors of individuals `rows` are
    not the recomputed ones bit for bit (the first that differs), or None."""
    for j, row in enumerate(rows):
        for what, a, b in zip(_CHECKED, claimed, recomputed, strict=True):
            if not _same_bits(a[j], b[j]):
                return (
                    f"worker {worker} run {run_id} generation {generation} individual {row}: "
                    f"claimed {what} {np.asarray(a[j]).tolist()!r}, recomputed "
                    f"{np.asarray(b[j]).tolist()!r}"
                )
    return None


def digest_error(result: Result, i: int, lease: Lease, loop: RunLoop) -> str | None:
    """Why generation `i` of `result` cannot count (None if it can): a span's worker must have
    evaluated the genomes `loop` asks for `lease`, else its GA differs (no more spans for it)."""
    if not result.digests:
        return "a span's generation without its digest" if lease.asked_by_worker else None
    if result.digests[i] == genome_digest(loop.ask()[lease.start : lease.stop]):
        return None
    return "evaluated other genomes than the server asked (its GA differs: another version?)"


def repeats_claim(
    config: RunConfig,
    generation: int,
    genome: np.ndarray,
    fitness: float,
    descriptors: tuple[Sequence[int], np.ndarray] | None = None,
) -> bool:
    """Whether this process's own evaluation of `genome` in `generation` gives the claimed
    `fitness`, and with `descriptors` (columns of DESCRIPTORS, values) those descriptors, bit
    for bit: what the server serves or reports on a worker's claim (a training rank, an archive
    elite) must pass this first, so no forged claim alone chooses it (docs/security.md)."""
    again = evaluate(config, generation, np.asarray(genome, dtype=np.float64)[None])
    if not _same_bits(np.array([fitness]), again.fitness):
        return False
    if descriptors is None:
        return True
    columns, values = descriptors
    return _same_bits(values, again.descriptors[0, list(columns)])


def _same_bits(claimed: np.ndarray, recomputed: np.ndarray) -> bool:
    """Bit for bit: a deterministic evaluation repeats every byte (-0.0 and NaN payloads too)."""
    a = np.ascontiguousarray(claimed, dtype="<f8")
    b = np.ascontiguousarray(recomputed, dtype="<f8")
    return a.shape == b.shape and a.tobytes() == b.tobytes()


_CHECKED = ("fitness", "components", "descriptors")
"""What a spot-check compares bit for bit, in this order."""
