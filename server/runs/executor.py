"""In-process evaluation: threads that lease jobs from the scheduler, evaluate them here, and
settle their results, as a remote worker does through the zenoh dispatcher (never spans)."""

from __future__ import annotations

import threading

from server.runs.evaluation import run_job
from server.runs.scheduler import Scheduler


class InProcessExecutor:
    """`threads` evaluation threads named `{name}-{i}` (their worker names in leases)."""

    def __init__(self, scheduler: Scheduler, *, threads: int = 1, name: str = "local") -> None:
        if threads < 0:
            raise ValueError(f"threads must be >= 0, got {threads}")
        self._scheduler = scheduler
        self._names = [f"{name}-{i}" for i in range(threads)]
        self._stop = threading.Event()
        self._wakes = {n: threading.Event() for n in self._names}
        """One per thread, so one thread clearing its event never hides a wake-up from another."""
        self._threads: list[threading.Thread] = []

    def _wake_all(self) -> None:
        for wake in self._wakes.values():
            wake.set()

    def start(self) -> None:
        """Start the threads; an idle thread sleeps until the scheduler has leasable jobs."""
        self._stop.clear()
        if not self._names:
            return
        self._scheduler.add_listener(self._wake_all)
        for worker in self._names:
            self._scheduler.join(worker, spans=False, listed=False)
        self._threads = [
            threading.Thread(target=self._loop, args=(n,), name=f"colony-{n}", daemon=True)
            for n in self._names
        ]
        for thread in self._threads:
            thread.start()

    def alive(self) -> bool:
        """Whether every thread started still runs (`/healthz`)."""
        return all(thread.is_alive() for thread in self._threads)

    def stop(self, timeout: float = 30.0) -> None:
        """Finish the job in hand, then stop (its result is settled)."""
        self._stop.set()
        self._wake_all()
        for thread in self._threads:
            thread.join(timeout=timeout)
        self._threads = []
        self._scheduler.remove_listener(self._wake_all)
        for worker in self._names:
            self._scheduler.leave(worker)

    def _loop(self, worker: str) -> None:
        wake = self._wakes[worker]
        while not self._stop.is_set():
            wake.clear()  # before leasing: an announcement from now on is not lost
            job = self._scheduler.lease(worker)
            if job is None:
                wake.wait()
                continue
            self._scheduler.settle(run_job(job, worker))
