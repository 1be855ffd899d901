"""The scheduler's worker table: every name that spoke, and its credential's standing.

A credential (the zenoh user, `credential`) is what a quarantine bans and what error results
count against: every worker named USER or USER.* (the names zenoh's roles let one credential
use) shares its fate. The table has no lock: the scheduler calls it under its own.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from schemas.wire import WorkerStatus
from server.runs.policy import Policy, clamp_speed


def credential(worker: str) -> str:
    """The zenoh user a worker's name belongs to: `USER` of `USER` or `USER.anything`
    (schemas.security.ZenohRoles; worker users contain no '.')."""
    return worker.partition(".")[0]


@dataclass
class Worker:
    """A name that spoke to the scheduler, as it sees it."""

    name: str
    host: str = ""
    threads: int = 1
    """Threads it evaluates on, as it claims: workers of one host on several share its cores
    (`Ledger.sliceable`), which a false claim can only waste."""
    speed: float | None = None
    """Robot-steps/s as it claims (clamped): spans and job sizes, which it can only waste."""
    measured: float | None = None
    """Robot-steps/s of its last accepted job, lease to result on the scheduler's clock: its
    leases, which a slow claim must not stretch."""
    jobs_done: int = 0
    evaluations: int = 0
    late: int = 0
    last_seen: float = 0.0
    """Unix time (for display only)."""
    asked_at: float | None = None
    """When it last asked for a job, on the scheduler's clock: only a name that asks counts
    as a worker (a credential can declare tokens for any number of names)."""
    gone_at: float | None = None
    serving: bool = True
    """False while it speaks another protocol: it is answered idle, never counted."""
    spans: bool = True
    """False for in-process evaluators, and once it evaluated genomes other than asked."""
    listed: bool = True
    """False for in-process evaluators: not shown as workers, never spot-checked (they run
    this process's own code)."""
    quarantine: str | None = None
    """Why it failed a spot-check: no more jobs, its results dropped, kept listed for good."""


class Workers:
    """Worker records by name, the quarantined credentials and the error streaks."""

    def __init__(
        self, policy: Policy, *, clock: Callable[[], float], wall: Callable[[], float]
    ) -> None:
        self._policy = policy
        self._clock = clock
        self._wall = wall
        self._records: dict[str, Worker] = {}
        self._banned: dict[str, str] = {}
        """Quarantined credentials (`credential(name)`) and why: a new name under one is too."""
        self._errors: dict[str, int] = {}
        """Credential -> its error results since its last accepted one."""

    def __getitem__(self, worker: str) -> Worker:
        return self._records[worker]

    def trusted(self, worker: str) -> bool:
        """An in-process executor (unlisted: it runs this process's own code); a name
        forgotten long ago was a worker's."""
        record = self._records.get(worker)
        return record is not None and not record.listed

    def touch(self, worker: str, *, revive: bool = True) -> Worker:
        """The worker's record, seen now; live again unless `revive` is False (a result
        arriving after its token vanished does not make it live: no token would end that)."""
        record = self._records.get(worker)
        if record is None:
            record = self._records[worker] = Worker(worker)
            record.quarantine = self._banned.get(credential(worker))
        record.last_seen = self._wall()
        if revive:
            record.gone_at = None
        return record

    def join(
        self,
        worker: str,
        *,
        host: str | None,
        threads: int,
        speed: float | None,
        serving: bool,
        spans: bool,
        listed: bool,
        asked: bool,
    ) -> None:
        """`worker` is alive, saying this of itself (`Scheduler.join`)."""
        record = self.touch(worker)
        if asked:
            record.asked_at = self._clock()
        record.serving = serving
        record.spans = record.spans and spans
        record.listed = record.listed and listed
        if host:
            record.host = host[:255]
        record.threads = threads
        if speed is not None:
            record.speed = clamp_speed(speed)

    def leave(self, worker: str) -> None:
        """`worker` is gone (its token vanished)."""
        record = self._records.setdefault(worker, Worker(worker))
        record.gone_at = self._clock()

    def statuses(self, busy: set[str]) -> list[WorkerStatus]:
        """Every listed worker, by name; those in `busy` hold a lease."""
        return [
            WorkerStatus(
                name=w.name,
                host=w.host,
                state="gone" if w.gone_at is not None else "busy" if w.name in busy else "idle",
                jobs_done=w.jobs_done,
                evaluations=w.evaluations,
                late=w.late,
                robot_steps_per_s=w.speed,
                last_seen=w.last_seen,
            )
            for w in sorted(self._records.values(), key=lambda w: w.name)
            if w.listed
        ]

    def quarantined(self) -> dict[str, str]:
        """Quarantined workers: name -> why."""
        return {w.name: w.quarantine for w in self._records.values() if w.quarantine}

    def forget_gone(self, now: float) -> None:
        """Drop the workers gone more than `gone_keep_s` before `now` (but the quarantined)."""
        for name, w in list(self._records.items()):
            if (
                w.gone_at is not None
                and w.quarantine is None
                and now - w.gone_at > self._policy.gone_keep_s
            ):
                del self._records[name]

    def live(self, busy: set[str]) -> list[Worker]:
        """Workers that take jobs: a token, and a lease held (`busy`) or asked for within
        `lease_max_s` (no lease lasts longer)."""
        since = self._clock() - self._policy.lease_max_s
        return [
            w
            for w in self._records.values()
            if w.gone_at is None
            and w.serving
            and w.quarantine is None
            and (w.name in busy or (w.asked_at is not None and w.asked_at >= since))
        ]

    def ban(self, name: str, why: str) -> str:
        """Quarantine `name`'s credential, every worker under it included; the credential."""
        banned = credential(name)
        self._banned[banned] = why
        for other in self._records.values():
            if credential(other.name) == banned:
                other.quarantine = why
        return banned

    def accepted(self, worker: str) -> None:
        """A result of `worker` counted: its credential's error streak ends."""
        self._errors.pop(credential(worker), None)

    def count_errors(self, erred: dict[str, tuple[str, str]]) -> list[tuple[str, str]]:
        """A job was evaluated without an error: each credential of `erred` (-> worker, error)
        erred on its own account. Those now `errors_quarantine` errors in a row and not yet
        quarantined, to quarantine: (worker, why) of each."""
        due = []
        for banned, (name, error) in erred.items():
            errors = self._errors[banned] = self._errors.get(banned, 0) + 1
            if errors >= self._policy.errors_quarantine and banned not in self._banned:
                due.append(
                    (
                        name,
                        f"worker {name}: {errors} error results in a row on jobs evaluated "
                        f"without one, the last: {error}",
                    )
                )
        return due
