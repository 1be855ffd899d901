"""Server time per generation outside evaluation (store + GA + bookkeeping), population 100.

Evaluation is done once up front and its results replayed, so the figure is the server's own
overhead: lease and complete every job, tell, commit the generation, ask the next. Target < 5 ms.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

from evorobotics.evaluate import evaluate
from schemas.run import RunConfig
from server.db import make_engine, upgrade
from server.jobs import JobResult
from server.manager import RunManager
from server.settings import Settings

GENERATIONS = 60


def main() -> None:
    config = RunConfig(generations=GENERATIONS + 1, steps=5, trials=1)
    with tempfile.TemporaryDirectory() as tmp:
        engine = make_engine(f"sqlite:///{Path(tmp) / 'bench.db'}")
        upgrade(engine)
        manager = RunManager(engine, Settings(db_url="unused"))
        manager.create_run(config)
        queue = manager.queue
        times: list[float] = []
        for _ in range(GENERATIONS):
            t0 = time.perf_counter()
            jobs = []
            while (job := queue.lease("bench", 0.0)) is not None:
                jobs.append(job)
            lease_s = time.perf_counter() - t0
            results = []
            for job in jobs:  # evaluation: not timed
                ev = evaluate(job.config, job.key.generation, job.genomes)
                results.append(JobResult(ev.fitness, ev.components))
            t0 = time.perf_counter()
            for job, result in zip(jobs, results, strict=True):
                queue.complete(job.key, result)
            times.append(lease_s + time.perf_counter() - t0)
        engine.dispose()
    ms = [t * 1e3 for t in times[5:]]
    print(
        f"server overhead per generation (population {config.population}, "
        f"{len(ms)} generations, {config.population // config.job_size} jobs): "
        f"median {statistics.median(ms):.2f} ms, p90 {sorted(ms)[int(0.9 * len(ms))]:.2f} ms "
        f"(target < 5 ms)"
    )


if __name__ == "__main__":
    main()
