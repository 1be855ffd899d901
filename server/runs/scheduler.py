"""The scheduler: every decision of the job path, as a state machine without I/O.

It decides who gets which job and whether a result counts. What is in flight (one `RunLoop`
per live run, its generation cut into jobs; reports; the one lease table on one injectable
clock; the worker table; the generations told but not yet written) is its ledger
(`server.runs.ledger`), which also completes what an accepted result finishes; the jobs no
worker may take are the referee's (`server.runs.referee`). Inputs are calls (a worker asks, a
result arrives, a worker leaves, the clock passes a deadline); outputs are jobs,
acknowledgements, told generations to store and runs to fail. It knows nothing of zenoh, HTTP
or the database; the zenoh dispatcher, the in-process executor and the run manager drive it,
each call under one lock held briefly.

A job is a contiguous slice of a generation. Only its lease holder's result counts: a late or
duplicate result is acknowledged as dropped. The result of the last job tells the run loop,
which asks the next generation at once. After the last generation the run's jobs are its
champion's stages (`server.runs.choosing`: candidates to validate, then test poses of the
pick), leased, retried, refereed and spot-checked as a generation's are; the last generation
goes to the store with the champion. A controller's report (`report`: an exploration report
or a robustness map, `evorobotics.reports`) is cut into jobs of its trials the same way, leased
before any run's, and assembled into the future its asker waits on (resolved outside the
lock); so is a ranking (`rank`: a run's candidates validated in a robot's world,
`evorobotics.evolution.rank_in_world`), cut into jobs of its candidates. A span lets the
worker holding a generation's only job evolve the following ones itself (ask and tell are
pure functions of the GA state and the seed): each accepted generation moves the lease on to
the next, and the worker proves with a digest that it evaluated the genomes asked here.

Spot-checks (`server.runs.evaluation`) evaluate again `Policy.spot_checks` individuals (a
stage's: rows) of every result of a listed worker: of a generation cut into several jobs, the
next job's worker does (`Job.checks`), and once all are in the ledger asks `cross_check` before
it tells; of anything else, this process does as the result arrives. A mismatch quarantines the worker's
credential for the life of the process (`server.runs.workers`): its workers get no more jobs
and its results in the generations (or the stage) in flight return to pending, so honest
workers evaluate them (docs/reliability.md, "Spot-checks").

Errors: a worker's error result says nothing about the run, only about that worker. Its job
returns to pending for other credentials; once `Policy.max_attempts` credentials erred on it, or
none other is live to take it, the server evaluates it itself (the referee's thread). Only the
server's own evaluation failing (the referee's, or an in-process executor's) fails a run. A
credential whose results err `Policy.errors_quarantine` times in a row is quarantined.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import TypeVar

import numpy as np

from evorobotics.evolution import Ranked, RunLoop
from evorobotics.reports import Report as Assembled
from evorobotics.strategies import traits
from schemas.run import RunConfig
from schemas.wire import Ack, Job, JobKey, ReportSpec, ReportStage, Result, WorkerStatus
from schemas.world import World
from server.core.logs import context
from server.runs.choosing import Choosing
from server.runs.evaluation import (
    cross_check,
    digest_error,
    implausible_claims,
    spot_check,
    spot_check_scores,
)
from server.runs.jobs import Lease, Rank, Report, Run, Slot
from server.runs.ledger import Ledger
from server.runs.outbox import Written
from server.runs.policy import Policy, clamp_speed
from server.runs.referee import REFEREE, Referee
from server.runs.workers import Worker, credential

log = logging.getLogger(__name__)

_Asked = TypeVar("_Asked", Report, Rank)

SPOT_TOTALS = ("results_checked", "individuals_checked", "robot_steps_checked", "mismatches")
"""Keys of `Scheduler.spot_totals()`."""


class Scheduler:
    """Jobs, leases, spans and workers of every live run; thread-safe, one lock per call."""

    def __init__(
        self,
        policy: Policy | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.policy = policy or Policy()
        self._clock = clock
        self._lock = threading.Lock()
        self._ledger = Ledger(self.policy, clock=clock, wall=wall)
        self._referee = Referee(self._ledger, self._lock, clock=clock, record=self._judged)
        self._ledger.verify = self._cross_check
        self.told_many = self._ledger.outbox.told_many
        """Set when a run has `write_now` generations unwritten: the store should write now."""
        self._closed = False
        self._spot = dict.fromkeys(SPOT_TOTALS, 0)
        self._listeners: list[Callable[[], None]] = []

    def now(self) -> float:
        """The scheduler's clock (leases and deadlines are on it)."""
        return self._clock()

    def close(self) -> None:
        """Finish the server's own evaluation in hand; no more after. Reports and rankings in
        flight fail (their askers stop waiting)."""
        self._referee.close()
        with self._lock:
            self._closed = True
            for report_id in list(self._ledger.reports):
                self._ledger.fail_report(report_id, "the server is stopping")
        self._resolve()

    # runs ------------------------------------------------------------------------------------

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call `listener` (it must not block) whenever jobs may have become leasable."""
        with self._lock:
            self._listeners.append(listener)

    def remove_listener(self, listener: Callable[[], None]) -> None:
        with self._lock:
            if listener in self._listeners:
                self._listeners.remove(listener)

    def add(self, run_id: int, loop: RunLoop, *, running: bool) -> None:
        """Serve `loop`'s current generation (replacing anything of the run in flight)."""
        with self._lock:
            self._ledger.drop_leases(run_id)
            self._ledger.install(run_id, loop, running, served=self._ledger.sequence)
        self._announce()

    def choose(self, run_id: int, loop: RunLoop, choosing: Choosing, *, running: bool) -> None:
        """Serve the champion's stages of a run whose `loop` is done (`choosing`, rebuilt from
        the store after a restart), replacing anything of the run in flight."""
        with self._lock:
            self._ledger.drop_leases(run_id)
            self._ledger.choose(
                run_id, loop, choosing, running=running, served=self._ledger.sequence
            )
        self._announce()

    def set_running(self, run_id: int, running: bool) -> None:
        """Pause (no new leases; leased jobs may still complete) or resume a run."""
        with self._lock:
            run = self._ledger.runs.get(run_id)
            if run is not None:
                run.running = running
        self._announce()

    def forget(self, run_id: int) -> None:
        """Drop a run (over): its results, if any arrive, are acknowledged as dropped."""
        with self._lock:
            self._ledger.drop_run(run_id)

    def take_told(self) -> list[Written]:
        """The generations told since the last call, oldest first, for the store."""
        with self._lock:
            return self._ledger.outbox.take()

    def written(self, told: list[Written]) -> None:
        """The store has `told` (or dropped it, its run being over): their runs may go on."""
        with self._lock:
            self._ledger.outbox.written(told)
        self._announce()

    def put_back(self, told: list[Written]) -> None:
        """Told generations the store refused: first in line for the next `take_told`."""
        with self._lock:
            self._ledger.outbox.put_back(told)

    def take_failed(self) -> dict[int, str]:
        """Runs (id -> why) whose job failed in the server's own evaluation since the last
        call: the store fails them (after writing their told generations)."""
        with self._lock:
            return self._ledger.outbox.take_failed()

    def put_back_failed(self, failed: dict[int, str]) -> None:
        """Failed runs the store could not record (its write refused): taken again next."""
        with self._lock:
            self._ledger.outbox.put_back_failed(failed)

    def has_pending(self) -> bool:
        with self._lock:
            return any(self._ledger.leasable(work) for work in self._ledger.work())

    # reports ---------------------------------------------------------------------------------

    def report(
        self, stage: ReportStage, config: RunConfig, spec: ReportSpec, weights: np.ndarray
    ) -> Future[Assembled]:
        """A controller's report (`evorobotics.reports`: `config` is
        `schemas.wire.report_config`) computed by jobs cut per live worker, leased before any
        run's; the future of the assembled report (or of the error that failed it: the
        server's own evaluation of one of its jobs, or the server stopping). The same report
        asked while in flight is the same future. ValueError for a bad request."""
        with self._lock:
            report = Report.new(
                stage, config, spec, weights, served=self._ledger.sequence, parts=self._parts()
            )
        return self._ask(report).future

    def rank(self, config: RunConfig, world: World, genomes: np.ndarray) -> Future[Ranked]:
        """`evorobotics.evolution.rank_in_world(config, genomes, world)`, computed by jobs
        of the candidates cut per live worker and leased before any run's, as a report is: the
        future of its (order, scores), bit for bit, or of the error that failed it. ValueError
        for bad candidates."""
        with self._lock:
            rank = Rank.new(
                config, world, genomes, served=self._ledger.sequence, parts=self._parts()
            )
        return self._ask(rank).future

    def _parts(self) -> int:
        """Jobs to cut asked work into: `jobs_per_worker` for each live worker."""
        return len(self._ledger.live()) * self.policy.jobs_per_worker

    def _ask(self, asked: _Asked) -> _Asked:
        """`asked` in flight, or the same work already in flight (its number is a digest of
        what it computes); failed at once if the scheduler is closed."""
        with self._lock:
            found = self._ledger.reports.get(asked.report_id)
            if isinstance(found, type(asked)):
                return found
            if self._closed:
                asked.future.set_exception(RuntimeError("the server is stopping"))
                return asked
            self._ledger.reports[asked.report_id] = asked
            self._referee.refer_stranded()  # a ranking while no worker is live
        self._announce()
        return asked

    # workers ---------------------------------------------------------------------------------

    def join(
        self,
        worker: str,
        *,
        host: str | None = None,
        threads: int = 1,
        speed: float | None = None,
        serving: bool = True,
        spans: bool = True,
        listed: bool = True,
        asked: bool = True,
    ) -> None:
        """`worker` is alive (a request, or only a token: `asked` False): noted with what it
        says of itself. An unlisted one (an in-process evaluator) leases like any other but is
        not in `workers`."""
        with self._lock:
            self._ledger.workers.join(
                worker,
                host=host,
                threads=threads,
                speed=speed,
                serving=serving,
                spans=spans,
                listed=listed,
                asked=asked,
            )

    def leave(self, worker: str) -> list[JobKey]:
        """`worker` is gone (its token vanished): its leases return at once; their keys."""
        with self._lock:
            self._ledger.workers.leave(worker)
            released = self._ledger.release_where(lambda lease: lease.worker == worker)
            self._referee.refer_stranded()
        self._announce()
        return released

    def workers(self) -> list[WorkerStatus]:
        """Every known worker, gone ones too until `gone_keep_s` after they left (quarantined
        ones for good)."""
        with self._lock:
            return self._ledger.workers.statuses(self._ledger.busy())

    def quarantined(self) -> dict[str, str]:
        """Workers that failed a spot-check: name -> why (worker, run, generation, individual,
        claimed and recomputed fitness)."""
        with self._lock:
            return self._ledger.workers.quarantined()

    # jobs ------------------------------------------------------------------------------------

    def lease(self, worker: str) -> Job | None:
        """The next job for `worker`, leased to it, or None. A worker asks only with empty
        hands, so a lease it still holds lost its reply: that job again, until that lease's
        deadline (asking again never extends a lease, nor trades it for another job)."""
        with self._lock:
            record = self._ledger.workers.touch(worker)
            now = record.asked_at = self._clock()
            self._ledger.lapse(lambda lease: lease.worker == worker and lease.deadline <= now)
            held = sorted(
                (lease for lease in self._ledger.leases.values() if lease.worker == worker),
                key=lambda lease: lease.leased_at,
            )
            self._ledger.release_where(lambda lease: lease.worker == worker)
            self._referee.refer_stranded()
            if record.quarantine is not None:
                return None
            chosen, index, kept = self._ledger.held_again(held)
            if chosen is None:
                excluded = credential(worker) if record.listed else None
                for work in self._ledger.work():
                    if not self._ledger.leasable(work) or (
                        chosen is not None and work.order >= chosen.order
                    ):
                        continue
                    pick = work.pick(excluded)
                    if pick is not None:
                        chosen, index = work, pick
            if chosen is None:
                return None
            chosen.unpend(index)
            span = 1
            if (
                isinstance(chosen, Run)
                and record.spans
                and len(chosen.slots) == 1
                and chosen.choosing is None
                and traits(chosen.config).in_state
            ):
                loop, config = chosen.loop, chosen.config
                alone = self._ledger.crowded() or not self._ledger.sliceable()
                wanted = self.policy.span_generations(config, record.speed, crowded=alone)
                span = max(1, min(wanted, config.generations - loop.generation))
            lease_s = self._ledger.lease(
                chosen, index, worker, span_left=span - 1, until=kept, now=now
            )
            return chosen.job(index, lease_s, span=span)

    def settle(self, result: Result) -> Ack:
        """Take a result: each of its generations in order while the worker holds the lease
        (a span's lease then moves on); an error is retried or fails the run."""
        with self._lock:
            ack = self._settle(result)
        self._resolve()
        self._announce()
        return ack

    def _settle(self, result: Result) -> Ack:
        record = self._ledger.workers.touch(result.worker, revive=False)
        if record.quarantine is not None:
            return Ack(key=result.key, accepted=False, reason="worker quarantined")
        if result.robot_steps_per_s > 0:
            record.speed = clamp_speed(result.robot_steps_per_s)
        forged = implausible_claims(result, self._ledger.find(result.key))
        if forged is not None:
            self._spot["mismatches"] += 1
            self._quarantine(record.name, forged)
            return Ack(key=result.key, accepted=False, reason=f"refused: {forged}")
        mismatch = self._spot_check(result, record)
        if mismatch is not None:
            self._spot["mismatches"] += 1
            self._quarantine(record.name, mismatch)
            return Ack(key=result.key, accepted=False, reason="spot-check failed: quarantined")
        ack = Ack(key=result.key, accepted=False, reason="no lease held: late or duplicate")
        following = result.key
        since, steps = math.nan, 0  # the message's first lease, and the robot-steps accepted
        for i in range(result.generations):
            key = result.key.at(result.key.generation + i)
            lease = self._ledger.leases.get(key)
            if (
                lease is None
                or lease.worker != result.worker
                or (
                    result.start is not None
                    and (result.start, result.stop) != (lease.start, lease.stop)
                )
            ):
                self._ledger.totals["duplicates_dropped"] += result.generations - i
                if result.fitness is not None:
                    record.late += (result.generations - i) * result.fitness.shape[1]
                break
            del self._ledger.leases[key]
            if result.error is not None:
                self._erred(key, record, result.error)
                ack = Ack(key=result.key, accepted=True, reason="error recorded")
                break
            work = self._ledger.find(key)
            if work is None:  # a lease never outlives its run or report
                raise ValueError(f"{key.label()} is leased but not in flight")
            if isinstance(work, Run) and work.choosing is None:
                checks = work.checks_of(key.index)
                asked = 0 if checks is None else len(checks)
                if result.checks != asked:  # as an error: never leased to it again
                    why = f"{result.checks} checks evaluated, its job asked for {asked}"
                    self._erred(key, record, why)
                    ack = Ack(key=result.key, accepted=True, reason="error recorded")
                    break
            wrong = digest_error(result, i, lease, work.loop) if isinstance(work, Run) else None
            if wrong is not None:
                record.spans = False
                context(log, worker=result.worker).warning(
                    "worker %s: %s; no more spans for it", result.worker, wrong
                )
                work.make_pending(key.index)  # asked here next time
                ack = Ack(key=result.key, accepted=True, reason="error recorded")
                break
            # a span's later leases are made as this message is taken: its speed is the
            # whole message's, from its first lease
            since = lease.leased_at if math.isnan(since) else since
            steps += work.robot_steps(lease.stop - lease.start)
            record.measured = clamp_speed(steps / max(self._clock() - since, 1e-6))
            self._accept(key, lease, result, i)
            if record.quarantine is not None:  # the generation's cross-checks caught it
                return Ack(key=result.key, accepted=False, reason="spot-check failed: quarantined")
            self._ledger.workers.accepted(result.worker)
            record.jobs_done += 1
            if key.stage == "train":  # a stage's rows are no controllers' fitness
                record.evaluations += lease.stop - lease.start
            ack = Ack(key=result.key, accepted=True)
            following = key.at(key.generation + 1)
        if ack.accepted and self._ledger.outbox.lags(result.key.run_id):
            # a span ends with the message that took its run too far ahead of the store
            self._ledger.release_where(
                lambda lease: lease.key == following and lease.worker == result.worker
            )
        return ack

    def expire(self) -> int:
        """Return every lease past its deadline; forget workers gone long ago (but the
        quarantined). The count."""
        now = self._clock()
        with self._lock:
            released = self._ledger.lapse(lambda lease: lease.deadline <= now)
            self._ledger.workers.forget_gone(now)
            self._referee.refer_stranded()
        if released:
            self._announce()
        return len(released)

    def next_deadline(self) -> float | None:
        """The clock time of the next lease deadline, if any (the referee's have none)."""
        with self._lock:
            deadlines = (lease.deadline for lease in self._ledger.leases.values())
            return min((d for d in deadlines if d < math.inf), default=None)

    def totals(self) -> dict[str, int]:
        """Since construction: jobs `leased`, results accepted (`done`), leases returned
        (`requeued`) and results dropped as late or duplicate (`duplicates_dropped`)."""
        with self._lock:
            return dict(self._ledger.totals)

    def spot_totals(self) -> dict[str, int]:
        """Since construction: results spot-checked, individuals and robot-steps re-evaluated,
        and mismatches (each quarantined a worker)."""
        with self._lock:
            return dict(self._spot)

    def counts(self) -> dict[str, int]:
        """Jobs of the generations in flight by status: pending, leased, done."""
        counts = {"pending": 0, "leased": 0, "done": 0}
        with self._lock:
            for work in self._ledger.work():
                for slot in work.slots:
                    counts[slot.status] += 1
        return counts

    # inside the lock -------------------------------------------------------------------------

    def _announce(self) -> None:
        with self._lock:
            listeners = list(self._listeners)
            ready = any(self._ledger.leasable(work) for work in self._ledger.work())
        if ready:
            for listener in listeners:
                listener()

    def _resolve(self) -> None:
        """Hand the reports and rankings finished or failed meanwhile to their askers (outside
        the lock: a future's callbacks run here)."""
        with self._lock:
            resolved = self._ledger.take_resolved()
        for resolve in resolved:
            resolve()

    def _accept(self, key: JobKey, lease: Lease, result: Result, i: int) -> None:
        """Generation `i` of `result` (or a stage's scores) fills the slot `lease` held
        (`Ledger.accept`), once the errors on it are counted."""
        work = self._ledger.find(key)
        if work is not None:
            self._count_errors(work.slots[key.index])
        self._ledger.accept(key, lease, result, i)

    def _spot_check(self, result: Result, record: Worker) -> str | None:
        """`spot_check` `result`, unless this process's own evaluator sent it (it runs this
        process's code)."""
        if not record.listed:
            return None
        lease, work = self._ledger.leases.get(result.key), self._ledger.find(result.key)
        if result.scores is not None:
            return spot_check_scores(
                result, lease, work, wanted=self.policy.spot_checks, totals=self._spot
            )
        run = work if isinstance(work, Run) else None
        if run is not None and run.check_rows:
            return None  # its rows are checked against the others' once all are in
        return spot_check(
            result,
            lease,
            run,
            wanted=self.policy.spot_checks,
            job_size=self._ledger.job_size,
            totals=self._spot,
        )

    def _cross_check(self, run: Run) -> None:
        """Quarantine each worker a complete generation's cross-checks caught
        (`cross_check`): its slots return to pending, and the generation waits for them."""
        liars = cross_check(run, trusted=self._trusted, totals=self._spot)
        for name, why in liars:
            if name not in self._ledger.workers.quarantined():
                self._spot["mismatches"] += 1
                self._quarantine(name, why)

    def _trusted(self, name: str) -> bool:
        """This process's own evaluation: the referee's, or an in-process executor's."""
        return name == REFEREE or self._ledger.workers.trusted(name)

    def _quarantine(self, name: str, why: str) -> None:
        """No more jobs for any worker of `name`'s credential; their leases and every result
        of them in the generations in flight return to pending."""
        banned = self._ledger.workers.ban(name, why)
        released = self._ledger.release_where(lambda lease: credential(lease.worker) == banned)
        discarded = sum(work.discard(banned) for work in self._ledger.work())
        context(log, worker=name).warning(
            "worker %s quarantined: %s; %d leases and %d results of it returned to pending",
            name,
            why,
            len(released),
            discarded,
        )
        self._referee.refer_stranded()  # no live worker may be left to take them

    def _erred(self, key: JobKey, record: Worker, error: str) -> None:
        """`record`'s evaluation of the job `key` erred: the run fails if it is the server's
        own; else the job goes to another credential, or to the referee when none is left. The
        error counts against the credential once someone evaluates the job without one."""
        work = self._ledger.find(key)
        if work is None:
            return
        if not record.listed:  # an in-process executor: this process's own evaluation
            self._ledger.fail_run(key, error)
            return
        slot = work.slots[key.index]
        slot.erred[credential(record.name)] = (record.name, error)
        work.erred = True
        work.make_pending(key.index)
        context(log, run=key.run_id, worker=record.name).warning(
            "worker %s: error result for %s, which returns to other workers: %s",
            record.name,
            key.label(),
            error,
        )
        self._referee.refer_stranded()

    def _count_errors(self, slot: Slot) -> None:
        """The slot's job is evaluated without an error: each credential that erred on it
        erred on its own account, and `errors_quarantine` such errors in a row quarantine it."""
        for name, why in self._ledger.workers.count_errors(slot.erred):
            self._quarantine(name, why)
        slot.erred = {}

    def _judged(self, job: Job, lease: Lease, result: Result) -> None:
        """The referee's `result` of `job`: accepted, or its run fails; nothing if `lease`
        ended meanwhile."""
        try:
            with self._lock:
                if self._ledger.leases.get(job.key) is not lease:
                    return
                del self._ledger.leases[job.key]
                if result.error is not None:
                    self._ledger.fail_run(job.key, result.error)
                else:
                    self._accept(job.key, lease, result, 0)
        except Exception as exc:  # a bug here must fail the run, not leave its job held
            log.exception("the server's evaluation of %s could not be recorded", job.key.label())
            with self._lock:
                if self._ledger.find(job.key) is not None:
                    self._ledger.fail_run(
                        job.key, f"the server's evaluation could not be recorded: {exc}"
                    )
        self._resolve()
        self._announce()
