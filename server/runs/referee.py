"""The referee: the server's own evaluation of the jobs no worker may evaluate.

A job that erred on `Policy.max_attempts` credentials, or on every live one, is leased to
`REFEREE` and evaluated on the referee's one thread (`run_job`), outside the scheduler's lock;
so is a ranking's job while no worker is live (a stuck robot's replacement must not wait for
one).
Its result goes back to the scheduler as a worker's would; only its failing fails the run (or
report), since a worker's error says nothing about the run.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from schemas.wire import Job, Result
from server.core.logs import context
from server.runs.evaluation import run_job
from server.runs.jobs import Lease, Rank, Work
from server.runs.ledger import Ledger
from server.runs.workers import credential

log = logging.getLogger(__name__)

REFEREE = "(server)"
"""The lease holder while the server evaluates a job itself (not a valid worker name)."""


class Referee:
    """Leases stranded jobs to `REFEREE` and evaluates them on its thread; `record` takes
    each result (it takes `lock`, and checks the lease still holds)."""

    def __init__(
        self,
        ledger: Ledger,
        lock: threading.Lock,
        *,
        clock: Callable[[], float],
        record: Callable[[Job, Lease, Result], None],
    ) -> None:
        self._ledger = ledger
        self._lock = lock
        self._clock = clock
        self._record = record
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="colony-referee")

    def close(self) -> None:
        """Finish the evaluation in hand; refer nothing more (such jobs stay pending)."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def refer_stranded(self) -> None:
        """Lease to the referee every pending job that erred on `max_attempts` credentials or
        that no live worker may take (each live credential erred on it), and a ranking's jobs
        while no worker is live. Under the lock."""
        ledger = self._ledger
        live = ledger.live()  # an in-process executor takes any job
        takers = None if any(not w.listed for w in live) else {credential(w.name) for w in live}
        for work in ledger.work():
            if not work.running:
                continue
            if isinstance(work, Rank) and takers is not None and not takers:
                for index in list(work.pending):
                    self._refer(work, index)
            elif work.erred:
                for index in work.stranded(ledger.policy.max_attempts, takers):
                    self._refer(work, index)

    def _refer(self, run: Work, index: int) -> None:
        """Lease pending slot `index` to the referee, whose thread evaluates it here (it
        stays pending if the referee has stopped: the scheduler is closing)."""
        slot = run.slots[index]
        job = run.job(index, self._ledger.policy.lease_max_s)
        key = job.key
        lease = Lease(key, REFEREE, math.inf, slot.start, slot.stop, self._clock())
        try:
            self._pool.submit(self._judge, job, lease)  # it waits for the lock
        except RuntimeError:
            return
        run.unpend(index)
        slot.status = "leased"
        self._ledger.leases[key] = lease
        erred = ", ".join(sorted(slot.erred))
        why = f"erred on {erred}" if erred else "no worker is live"
        context(log, run=key.run_id).info("%s %s: the server evaluates it", key.label(), why)

    def _judge(self, job: Job, lease: Lease) -> None:
        """The referee's thread: evaluate `job` and record it; nothing if `lease` ended
        meanwhile (its run dropped, replaced or resumed anew)."""
        with self._lock:
            if self._ledger.leases.get(job.key) is not lease:
                return
        self._record(job, lease, run_job(job, "server"))  # the lease stays REFEREE's
