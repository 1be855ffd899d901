"""The store: server time per generation outside evaluation, and a paper run's size on disk.

1. Server time per generation outside evaluation (store + GA + bookkeeping), population 100.

Evaluation is done once per generation outside the clock, so the figure is the server's own
overhead: lease and complete every job, tell, commit the generation, ask the next. Target < 5 ms.
Also printed: the part spent in the final `complete` as the zenoh dispatcher calls it
(`defer=True`: tell, ask and install the next generation, the part between the last result and
the next jobs), the deferred `flush` (the generation's one transaction, while workers already
evaluate the next), and the machine's load average, since a busy disk or CPU moves these.

2. The default experiment (350 generations) written by the manager, evaluated outside it, at
   the default checkpoint interval and with every generation a checkpoint: the database's
   bytes (target at most 2 MB), and the time to rebuild a generation's individuals with their
   components (`crud.ranked`, as `GET /api/runs/{id}/individuals` reads them; target < 1 s),
   worst over the generations sampled.

    .venv/bin/python bench/store.py [--only overhead|size]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from schemas.run import RunConfig
from schemas.wire import Job
from server.core.db import make_engine, upgrade
from server.core.settings import CHECKPOINT_EVERY, Settings
from server.runs import crud
from server.runs.evaluation import run_job
from server.runs.lifecycle import RunManager

GENERATIONS = 60
WARMUP = 5


def _summary(name: str, seconds: list[float]) -> str:
    ms = sorted(t * 1e3 for t in seconds[WARMUP:])
    return f"{name}: median {statistics.median(ms):.2f} ms, p90 {ms[int(0.9 * len(ms))]:.2f} ms"


def size(every: int) -> tuple[int, float, int]:
    """(database bytes, slowest rebuild in seconds, its generation) of a default paper run
    stored with a checkpoint every `every` generations."""
    config = RunConfig()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.db"
        engine = make_engine(f"sqlite:///{path}")
        upgrade(engine)
        manager = RunManager(engine, Settings(db_url="unused", checkpoint_every=every))
        run_id = manager.create_run(config)
        while (job := manager.scheduler.lease("bench")) is not None:
            manager.scheduler.settle(run_job(job, "bench"))
            manager.flush()
        with engine.connect() as conn:
            conn.exec_driver_sql("VACUUM")
        slowest = (0.0, -1)
        with manager.sessions() as session:
            crud.ranked(session, run_id=run_id, generation=1, components=True)  # warm kernel
            for g in [*range(0, config.generations, 7), max(every - 2, 0), every - 1]:
                t0 = time.perf_counter()
                crud.ranked(session, run_id=run_id, generation=min(g, 349), components=True)
                slowest = max(slowest, (time.perf_counter() - t0, min(g, 349)))
        engine.dispose()
        return path.stat().st_size, slowest[0], slowest[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", choices=("overhead", "size"))
    args = parser.parse_args()
    if args.only != "size":
        overhead()
    if args.only != "overhead":
        for every in (CHECKPOINT_EVERY, 1):
            stored, seconds, g = size(every)
            print(
                f"paper run (350 generations) with a checkpoint every {every}: "
                f"{stored / 1e6:.2f} MB (target at most 2 MB at the default); slowest rebuild "
                f"{seconds * 1e3:.1f} ms (generation {g}; target < 1 s)"
            )


def overhead() -> None:
    config = RunConfig(generations=GENERATIONS + 1, steps=5, trials=1)
    load = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        engine = make_engine(f"sqlite:///{Path(tmp) / 'bench.db'}", background_checkpoint=True)
        upgrade(engine)
        manager = RunManager(engine, Settings(db_url="unused", span_below_seconds=0))
        manager.create_run(config)
        scheduler = manager.scheduler
        totals: list[float] = []
        advances: list[float] = []
        writes: list[float] = []
        for _ in range(GENERATIONS):
            t0 = time.perf_counter()
            jobs: list[Job] = []
            while (job := scheduler.lease(f"bench-{len(jobs)}")) is not None:
                jobs.append(job)
            lease_s = time.perf_counter() - t0
            results = [run_job(job, f"bench-{i}") for i, job in enumerate(jobs)]  # not timed
            t0 = time.perf_counter()
            for result in results[:-1]:
                scheduler.settle(result)
            t1 = time.perf_counter()
            scheduler.settle(results[-1])
            t2 = time.perf_counter()
            manager.flush()
            t3 = time.perf_counter()
            totals.append(lease_s + t3 - t0)
            advances.append(t2 - t1)
            writes.append(t3 - t2)
        engine.dispose()
    print(
        f"server overhead per generation (population {config.population}, "
        f"{GENERATIONS - WARMUP} generations, {len(jobs)} jobs, load average "
        f"{load[0]:.2f}): "
        + _summary("total", totals)
        + " (target < 5 ms); of which "
        + _summary("last result to next jobs", advances)
        + "; "
        + _summary("deferred write", writes)
    )


if __name__ == "__main__":
    main()
