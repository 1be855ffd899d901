"""In-process evaluation: threads that lease jobs, evaluate them here, and complete them.

It uses only the queue's public seam (lease / complete / fail), exactly as a remote worker
does through the zenoh dispatcher, so swapping executors changes no run logic.
"""

from __future__ import annotations

import threading
import time

from evorobotics.evaluate import evaluate
from server.jobs import JobQueue, JobResult
from server.manager import RunManager

IDLE_WAIT_S = 0.5
"""Longest an idle executor sleeps before polling again (it is woken when jobs arrive)."""


class InProcessExecutor:
    """`threads` evaluation threads named `{name}-{i}` (their worker ids in leases)."""

    def __init__(self, manager: RunManager, *, threads: int = 1, name: str = "local") -> None:
        if threads < 0:
            raise ValueError(f"threads must be >= 0, got {threads}")
        self._manager = manager
        self._queue: JobQueue = manager.queue
        self._names = [f"{name}-{i}" for i in range(threads)]
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> None:
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._loop, args=(n,), name=f"colony-{n}", daemon=True)
            for n in self._names
        ]
        for thread in self._threads:
            thread.start()

    def stop(self, timeout: float = 30.0) -> None:
        """Finish the job in hand, then stop (its result is stored)."""
        self._stop.set()
        self._queue.work_available.set()
        for thread in self._threads:
            thread.join(timeout=timeout)
        self._threads = []

    def _loop(self, worker: str) -> None:
        queue = self._queue
        while not self._stop.is_set():
            queue.work_available.clear()
            job = queue.lease(worker, time.time())
            if job is None:
                queue.work_available.wait(IDLE_WAIT_S)
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
