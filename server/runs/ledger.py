"""What the scheduler has in flight, and what an accepted result completes.

The ledger holds the runs and reports in flight (`server.runs.jobs`), the one lease table, the
worker table (`server.runs.workers`) and the told generations on their way to the store
(`server.runs.outbox`). A result the scheduler accepted fills its slot here: the last of a
generation tells the run loop, which asks the next generation at once (a span's lease moves on
to it); the last of a champion's stage moves the choice on (`server.runs.choosing`), and once
no stage is left the last generation goes to the store with the champion; the last of a report
or a ranking assembles it (`evorobotics.reports`, `evorobotics.evolution.ranked`) for its
asker's future, which the scheduler resolves outside its lock. No lock: the scheduler calls it
under its own.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from functools import partial

import numpy as np

from evorobotics.evolution import RunLoop
from schemas.run import RunConfig
from schemas.wire import JobKey, Result
from server.runs.choosing import Choosing
from server.runs.jobs import AskedWork, Lease, Run, Work
from server.runs.outbox import Outbox, Written
from server.runs.policy import Policy
from server.runs.workers import Worker, Workers, credential

log = logging.getLogger(__name__)

TOTALS = ("leased", "done", "requeued", "duplicates_dropped")
"""Keys of `Ledger.totals` (`Scheduler.totals`)."""


class Ledger:
    """Runs, reports and rankings, leases, workers and told generations in flight, and their
    completion."""

    def __init__(
        self, policy: Policy, *, clock: Callable[[], float], wall: Callable[[], float]
    ) -> None:
        self.policy = policy
        self._clock = clock
        self.runs: dict[int, Run] = {}
        self.reports: dict[int, AskedWork] = {}
        """Reports and rankings by number."""
        self.leases: dict[JobKey, Lease] = {}
        self.workers = Workers(policy, clock=clock, wall=wall)
        self.outbox = Outbox(policy, clock)
        self.sequence = 0
        """Leases made so far: a work's `served` is the number of its last."""
        self.totals = dict.fromkeys(TOTALS, 0)
        self.verify: Callable[[Run], None] = lambda run: None
        """Judges a generation's slots against each other once all are in (the scheduler's
        cross-checks); any it quarantines return to pending, and the generation waits."""
        self._resolved: list[Callable[[], None]] = []
        """What resolves the futures of the reports and rankings finished or failed, for the
        scheduler to call outside its lock (a future's callbacks run there)."""

    def take_resolved(self) -> list[Callable[[], None]]:
        """What resolves the reports and rankings finished (their result) or failed (the
        error) since the last call."""
        resolved, self._resolved = self._resolved, []
        return resolved

    # what is in flight -----------------------------------------------------------------------

    def work(self) -> Iterator[Work]:
        """Everything in flight: reports and rankings, then runs."""
        yield from self.reports.values()
        yield from self.runs.values()

    def find(self, key: JobKey) -> Work | None:
        """The report, ranking or run whose job `key` is, if in flight."""
        return self.reports.get(key.run_id) if key.report else self.runs.get(key.run_id)

    def leasable(self, work: Work) -> bool:
        """Running, with a job pending, and (a run's) its store keeping up."""
        lags = isinstance(work, Run) and self.outbox.lags(work.run_id)
        return work.running and bool(work.pending) and not lags

    def busy(self) -> set[str]:
        """The workers holding a lease."""
        return {lease.worker for lease in self.leases.values()}

    def live(self) -> list[Worker]:
        """Workers that take jobs (`Workers.live`)."""
        return self.workers.live(self.busy())

    def crowded(self, run_id: int | None = None) -> bool:
        """At least as many running runs (`run_id` counted as one) as jobs the live workers
        take (`jobs_per_worker` each): each job can be a run's whole generation, so slicing a
        generation only adds round trips."""
        live = len(self.live()) * self.policy.jobs_per_worker
        running = {run.run_id for run in self.runs.values() if run.running}
        return live > 0 and len(running | ({run_id} if run_id is not None else set())) >= live

    def sliceable(self) -> bool:
        """Whether cutting a generation between the live workers gains anything: they take
        more than one job (`jobs_per_worker` each), the workers of one host that evaluate on
        several threads counting as one worker (they share its cores)."""
        live = self.live()
        shared = {w.host for w in live if w.threads > 1}
        units = len(shared) + sum(1 for w in live if w.threads == 1)
        return units * self.policy.jobs_per_worker > 1

    def job_size(self, config: RunConfig, generation: int, run_id: int | None) -> int:
        """`Policy.job_size` for the live workers, `run_id` counted among the running runs;
        workers that are not `sliceable` count as crowded (each job a whole generation)."""
        live = self.live()
        speeds = [w.speed if w.spans else None for w in live]
        crowded = bool(live) and (self.crowded(run_id) or not self.sliceable())
        return self.policy.job_size(config, generation, speeds, crowded=crowded)

    def install(self, run_id: int, loop: RunLoop, running: bool, served: int) -> None:
        """Serve `loop`'s current generation, cut into jobs for the live workers."""
        size = self.job_size(loop.config, loop.generation, run_id if running else None)
        self.runs[run_id] = Run.new(
            run_id, loop, running=running, served=served, size=size, checks=self.policy.spot_checks
        )

    # leases ----------------------------------------------------------------------------------

    def lease(
        self,
        run: Work,
        index: int,
        worker: str,
        *,
        span_left: int = 0,
        asked_by_worker: bool = False,
        until: Lease | None = None,
        now: float | None = None,
    ) -> float:
        """Lease slot `index` of the run's generation to `worker` at `now` (None: the clock's
        now); the lease's seconds, from the slot's robot-steps and the worker's speed, or what
        is left of `until` (the lease it held of the same job, whose deadline is past `now`:
        asking again never extends one)."""
        slot = run.slots[index]
        now = self._clock() if now is None else now
        if until is None:
            lease_s = self.policy.lease_seconds(
                run.robot_steps(slot.stop - slot.start), self.workers[worker].measured
            )
            deadline, leased_at = now + lease_s, now
        else:
            deadline, leased_at = until.deadline, until.leased_at
            lease_s = max(deadline - now, 0.0)
        slot.status = "leased"
        if isinstance(run, Run):
            run.show(index, worker)
        self.sequence += 1
        run.served = self.sequence
        key = run.key(index)
        self.leases[key] = Lease(
            key, worker, deadline, slot.start, slot.stop, leased_at, span_left, asked_by_worker
        )
        self.totals["leased"] += 1
        return lease_s

    def release_where(self, condition: Callable[[Lease], bool]) -> list[JobKey]:
        """Return to pending every leased job whose lease meets `condition`; their keys."""
        released = [lease for lease in self.leases.values() if condition(lease)]
        for lease in released:
            del self.leases[lease.key]
            work = self.find(lease.key)
            if work is not None and work.key(lease.key.index) == lease.key:
                work.make_pending(lease.key.index)
        self.totals["requeued"] += len(released)
        return [lease.key for lease in released]

    def lapse(self, condition: Callable[[Lease], bool]) -> list[JobKey]:
        """Return to pending the leases meeting `condition`, each ending without its result:
        never leased again to its holder's credential (no error counts against it; the
        referee's once no other live credential may take it), so no worker holds a job for
        good by letting its lease expire. An in-process executor's lease just returns. The
        keys."""
        lapsed = [lease for lease in self.leases.values() if condition(lease)]
        released = self.release_where(condition)
        for lease in lapsed:
            work = self.find(lease.key)
            if work is None or work.key(lease.key.index) != lease.key:
                continue
            if not self.workers.trusted(lease.worker):
                work.slots[lease.key.index].lapsed.add(credential(lease.worker))
                work.erred = True
        return released

    def held_again(self, held: list[Lease]) -> tuple[Work | None, int, Lease | None]:
        """(work, slot, lease) of the first of `held` (leases just released from a worker that
        asked again) whose job is still to be done, or (None, 0, None)."""
        for lease in held:
            work = self.find(lease.key)
            index = lease.key.index
            if (
                work is not None
                and work.key(index) == lease.key
                and self.leasable(work)
                and index in work.pending
            ):
                return work, index, lease
        return None, 0, None

    def drop_run(self, run_id: int) -> None:
        """The run is over: its work, leases and unwritten generations go."""
        self.runs.pop(run_id, None)
        self.outbox.drop(run_id)
        self.drop_leases(run_id)

    def drop_leases(self, run_id: int) -> None:
        for key in [k for k in self.leases if k.run_id == run_id and not k.report]:
            del self.leases[key]

    # completion ------------------------------------------------------------------------------

    def accept(self, key: JobKey, lease: Lease, result: Result, i: int) -> None:
        """Generation `i` of `result` (or a stage's scores) fills the slot `lease` held."""
        if result.scores is not None and key.report:
            self._complete_report(key, lease, result.scores)
        elif result.scores is not None:
            self._complete_stage(key, lease, result.scores)
        elif (
            result.fitness is not None
            and result.components is not None
            and result.descriptors is not None
        ):
            fitness, components, descriptors = result.fitness, result.components, result.descriptors
            self._complete(key, lease, fitness[i], components[i], descriptors[i])

    def _complete(
        self,
        key: JobKey,
        lease: Lease,
        fitness: np.ndarray,
        components: np.ndarray,
        descriptors: np.ndarray,
    ) -> None:
        run = self.runs[key.run_id]
        run.fill(key.index, lease.worker, fitness, components, descriptors)
        self.totals["done"] += 1
        if run.remaining:
            return
        self.verify(run)
        if run.remaining:
            return
        loop = run.loop
        told = loop.tell(run.fitness, run.components, run.descriptors)
        if loop.done:
            try:
                choosing = Choosing.new(run.run_id, loop, told)
            except ValueError as exc:
                self._fail_choice(run.run_id, exc)
                return
            self.choose(run.run_id, loop, choosing, running=run.running, served=run.served)
            return
        self.outbox.tell(Written(run.run_id, loop.config, told))
        self.install(run.run_id, loop, run.running, served=run.served)
        following = self.runs[run.run_id]
        if lease.span_left > 0 and following.running and len(following.slots) == 1:
            following.unpend(0)
            self.lease(
                following, 0, lease.worker, span_left=lease.span_left - 1, asked_by_worker=True
            )

    def _complete_report(self, key: JobKey, lease: Lease, scores: np.ndarray) -> None:
        report = self.reports[key.run_id]
        try:
            resolve = report.fill_scores(key.index, lease.worker, scores)
        except ValueError as exc:
            self.fail_report(report.report_id, f"it cannot be assembled: {exc}")
            return
        self.totals["done"] += 1
        if resolve is not None:
            self._resolved.append(resolve)
            del self.reports[report.report_id]

    def _complete_stage(self, key: JobKey, lease: Lease, scores: np.ndarray) -> None:
        run = self.runs[key.run_id]
        try:
            choosing = run.fill_scores(key.index, lease.worker, scores)
        except ValueError as exc:
            self._fail_choice(run.run_id, exc)
            return
        self.totals["done"] += 1
        if choosing is not None:
            self.choose(run.run_id, run.loop, choosing, running=run.running, served=run.served)

    def choose(
        self, run_id: int, loop: RunLoop, choosing: Choosing, *, running: bool, served: int
    ) -> None:
        """Serve `choosing`'s stage in hand, cut into a job per live worker (`jobs_per_worker`
        each); once none is left, the last generation goes to the store with its champion."""
        if choosing.stage is None:
            try:
                written = choosing.written()
            except ValueError as exc:
                self._fail_choice(run_id, exc)
                return
            self.outbox.tell(written)
            self.runs.pop(run_id, None)
            return
        parts = len(self.live()) * self.policy.jobs_per_worker
        self.runs[run_id] = Run.choose(
            run_id, loop, choosing, running=running, served=served, parts=parts
        )

    # failures --------------------------------------------------------------------------------

    def _fail_choice(self, run_id: int, exc: ValueError) -> None:
        """The run's champion cannot be chosen (no candidate, or a bug): the run fails."""
        log.error("run %d: its champion cannot be chosen: %s", run_id, exc)
        self.outbox.fail(run_id, f"its champion cannot be chosen: {exc}")
        self.drop_run(run_id)

    def fail_report(self, report_id: int, why: str) -> None:
        """The report or ranking fails (its asker gets the error); its jobs are dropped."""
        report = self.reports.pop(report_id)
        log.warning("%s failed: %s", report.label, why)
        error = RuntimeError(f"{report.label} failed: {why}")
        self._resolved.append(partial(report.future.set_exception, error))
        for key in [k for k in self.leases if k.report and k.run_id == report_id]:
            del self.leases[key]

    def fail_run(self, key: JobKey, error: str) -> None:
        """The server's own evaluation of job `key` failed: its run (or report, or ranking)
        fails."""
        if key.report:
            self.fail_report(key.run_id, f"the server's own evaluation failed: {error}")
            return
        self.outbox.fail(
            key.run_id,
            f"job {key.generation}/{key.index} failed in the server's own evaluation: {error}",
        )
        self.drop_run(key.run_id)
