"""In-process evaluation: threads that lease jobs, evaluate them here, and complete them.

It uses only the queue's public seam (lease / complete / fail), exactly as a remote worker
does through the zenoh dispatcher, so swapping executors changes no run logic.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from evorobotics.evaluate import evaluate
from server.jobs import JobQueue, JobResult
from server.manager import RunManager


class InProcessExecutor:
    """`threads` evaluation threads named `{name}-{i}` (their worker ids in leases)."""

    def __init__(self, manager: RunManager, *, threads: int = 1, name: str = "local") -> None:
        if threads < 0:
            raise ValueError(f"threads must be >= 0, got {threads}")
        self._manager = manager
        self._queue: JobQueue = manager.queue
        self._names = [f"{name}-{i}" for i in range(threads)]
        self._stop = threading.Event()
        self._wakes = {n: threading.Event() for n in self._names}
        """One per thread, so one thread clearing its event never hides a wake-up from another."""
        self._remove_listener: Callable[[], None] | None = None
        self._threads: list[threading.Thread] = []

    def _wake_all(self) -> None:
        for wake in self._wakes.values():
            wake.set()

    def start(self) -> None:
        """Start the threads; an idle thread sleeps until the queue announces leasable jobs."""
        self._stop.clear()
        if self._remove_listener is None:
            self._remove_listener = self._queue.add_listener(self._wake_all)
        self._threads = [
            threading.Thread(target=self._loop, args=(n,), name=f"colony-{n}", daemon=True)
            for n in self._names
        ]
        for thread in self._threads:
            thread.start()

    def stop(self, timeout: float = 30.0) -> None:
        """Finish the job in hand, then stop (its result is stored)."""
        self._stop.set()
        self._wake_all()
        for thread in self._threads:
            thread.join(timeout=timeout)
        self._threads = []
        if self._remove_listener is not None:
            self._remove_listener()
            self._remove_listener = None

    def _loop(self, worker: str) -> None:
        queue, wake = self._queue, self._wakes[worker]
        while not self._stop.is_set():
            wake.clear()  # before leasing: an announcement from now on is not lost
            job = queue.lease(worker, time.time())
            if job is None:
                wake.wait()
                continue
            try:
                evaluation = evaluate(job.config, job.key.generation, job.genomes)
            except Exception as exc:  # an evaluation error is the run's problem, not the thread's
                queue.fail(job.key, f"{type(exc).__name__}: {exc}")
                continue
            try:
                queue.complete(job.key, JobResult(evaluation.fitness, evaluation.components))
            except Exception as exc:  # the generation could not be committed: fail that run
                self._manager.fail_run(
                    job.key.run_id, f"generation {job.key.generation}: {type(exc).__name__}: {exc}"
                )
