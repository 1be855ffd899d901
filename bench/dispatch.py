"""Dispatch throughput and distributed wall time (prints figures; no assertions).

1. jobs/s through a real Dispatcher and Scheduler with empty jobs (endless runs of a tiny
   population whose generations the scheduler cuts into one job per worker and tells, spans
   off; workers in spawned processes run `run_worker` with an evaluator that returns zeros):
   the job path's own ceiling, the GA's ask and tell of a 4-genome population included; and
   what one such job costs on each side in one process, caches warm (the message codecs and
   the scheduler's settle and lease: the part of the per-job CPU that is this project's
   Python, not zenoh's).
2. `colony evolve` alone and two side by side: how much two processes get from the cores.
3. A stuck robot's `fit` ranking as jobs of worker processes (`Scheduler.rank`) against the
   same ranking in the server's process (`rank_in_world`): wall time and the server's CPU.
4. The default experiment on `colony server --workers 2` (a subprocess: REST, the run manager,
   zenoh on loopback, two local worker processes), against `evolve` in this process, with the
   best controllers compared, and the CPU seconds each side used: what the machine's cores
   must run for the distributed run, against what `colony evolve` runs on one.

    .venv/bin/python bench/dispatch.py [--seconds 5] [--windows 3] [--rounds 5000] [--workers 2]
        [--generations 350] [--steps 240] [--repeats 3] [--sweep] [--span-below SECONDS]
        [--only throughput|paper|rank]

`--steps 240` is the default trial (three crossings of the paper maze); `--steps 2400
--generations 35` is the same number of robot-steps with ten times the work per generation:
the coordination cost per generation weighs a tenth as much. `--sweep` also times 400 to
1,600 steps (generations scaled to the same robot-steps) on the same server and
prints where the distributed run catches up with `colony evolve`. `--span-below` sets the
server's COLONY_SPAN_BELOW_SECONDS (0: every generation in parallel slices, no spans).
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing as mp
import os
import socket
import statistics
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from _procs import children, cpu_seconds

from evorobotics.evaluate import trial_steps
from evorobotics.evolution import RunLoop
from schemas.run import RunConfig
from schemas.wire import Ack, Result, decode, decode_result_reply, encode
from server.core.settings import Settings
from server.runs.dispatch import Dispatcher, DispatchSettings
from server.runs.lifecycle import WRITE_AFTER_S
from server.runs.policy import Policy
from server.runs.scheduler import Scheduler
from worker.main import WorkerSettings, run_worker

EMPTY = RunConfig(population=4, job_size=1, trials=1, steps=1, generations=100_000)
"""The empty jobs' run: the smallest population the GA takes, one robot-step per individual."""
NO_SPANS = Policy(span_below_s=0)
"""Every generation cut into jobs: spans would keep empty generations off the wire."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def zeros(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = genomes.shape[0]
    return np.zeros(n), np.zeros((n, config.trials, 4)), np.zeros((n, 4))


def worker_process(port: int, name: str, empty: bool, stopping: threading.Event) -> None:
    """`run_worker` as `colony worker` runs it: on a threading.Event (the loop checks it a few
    times a job; a multiprocessing.Event costs a semaphore round each), set from `stopping`."""
    settings = WorkerSettings(connect=(f"tcp/127.0.0.1:{port}",), name=name, backoff_max_s=0.2)
    stop = threading.Event()

    def relay() -> None:
        stopping.wait()
        stop.set()

    threading.Thread(target=relay, name="stop-relay", daemon=True).start()
    if empty:
        run_worker(settings, stop, evaluator=zeros)
    else:
        run_worker(settings, stop)


class EndlessRuns:
    """Empty runs on a real scheduler, one after another: a thread takes the told generations
    as the run manager's writer does (without storing them) and adds the next run
    when one ends."""

    def __init__(self, scheduler: Scheduler) -> None:
        self.scheduler = scheduler
        self.generations = 0
        self._runs = 1
        scheduler.add(self._runs, RunLoop(EMPTY), running=True)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._drain, name="drain", daemon=True)
        self._thread.start()

    @property
    def jobs(self) -> int:
        return self.scheduler.totals()["done"]

    def _drain(self) -> None:
        while not self._stop.is_set():
            self.scheduler.told_many.wait(WRITE_AFTER_S)
            self.scheduler.told_many.clear()
            self._take()

    def _take(self) -> None:
        taken = self.scheduler.take_told()
        self.scheduler.written(taken)  # as the run manager does once it has stored them
        for written in taken:
            self.generations += 1
            if written.last:
                self._runs += 1
                self.scheduler.add(self._runs, RunLoop(EMPTY), running=True)

    def close(self) -> None:
        """Stop the thread; count what was told since its last round."""
        self._stop.set()
        self._thread.join(timeout=10)
        self._take()


def start_workers(
    ctx: mp.context.SpawnContext, port: int, n: int, empty: bool
) -> tuple[list[mp.process.BaseProcess], threading.Event]:
    stop = ctx.Event()
    procs = [
        ctx.Process(target=worker_process, args=(port, f"bench-{i}", empty, stop)) for i in range(n)
    ]
    for p in procs:
        p.start()
    return procs, stop  # type: ignore[return-value]


def stop_workers(procs: list[mp.process.BaseProcess], stop: threading.Event) -> None:
    stop.set()
    for p in procs:
        p.join(timeout=30)


def bench_throughput(seconds: float, workers: int, windows: int) -> None:
    """Empty jobs through the dispatcher over `windows` consecutive windows of `seconds` on the
    same workers (this VM's speed moves by 15 % within a minute), with each side's CPU."""
    ctx = mp.get_context("spawn")
    port = free_port()
    scheduler = Scheduler(NO_SPANS)
    runs = EndlessRuns(scheduler)
    rates: list[float] = []
    server_us: list[float] = []
    workers_us: list[float] = []
    try:
        with Dispatcher(DispatchSettings(listen=(f"tcp/127.0.0.1:{port}",)), scheduler):
            procs, stop = start_workers(ctx, port, workers, empty=True)
            pids = [p.pid for p in procs if p.pid is not None]
            warm = threading.Event()
            deadline = time.monotonic() + 120  # spawned interpreters import numpy and zenoh
            while runs.jobs < 50:
                if time.monotonic() > deadline:
                    stop_workers(procs, stop)
                    raise TimeoutError(f"{runs.jobs} empty jobs done in 120 s: no workers?")
                warm.wait(0.05)
            for _ in range(windows):
                before, began = runs.jobs, time.perf_counter()
                server_before, workers_before = time.process_time(), cpu_seconds(pids)
                warm.wait(seconds)
                done, elapsed = runs.jobs - before, time.perf_counter() - began
                rates.append(done / elapsed)
                if done:  # a window without a job (workers stalled) has no CPU per job
                    server_us.append((time.process_time() - server_before) / done * 1e6)
                    workers_us.append((cpu_seconds(pids) - workers_before) / done * 1e6)
            # Stopped workers leave holding the job they were given: expected, not a warning.
            logging.getLogger("server.runs.dispatch").setLevel(logging.ERROR)
            stop_workers(procs, stop)
    finally:
        runs.close()
    per_generation = runs.jobs / max(runs.generations, 1)
    print(
        f"empty jobs: {statistics.median(rates):8.0f} jobs/s, median of {windows} windows of "
        f"{seconds:g} s [{min(rates):.0f}-{max(rates):.0f}] "
        f"({per_generation:.2f} jobs a generation of {EMPTY.population} genomes, no spans; "
        f"{workers} worker processes, load average {os.getloadavg()[0]:.2f}); CPU per job: "
        + (
            f"server {statistics.median(server_us):.0f} us, workers "
            f"{statistics.median(workers_us):.0f} us"
            if server_us
            else "no job done"
        )
    )


def bench_codec(rounds: int = 5_000) -> None:
    """One worker's empty jobs through a scheduler and the codecs, `rounds` times in one
    process, each side timed apart (best of three): the server reads a result, settles it
    (the generation's tell and the next ask), leases the next job and writes it with the Ack;
    the worker reads that reply and writes its result asking for the next."""
    costs = [float("inf"), float("inf")]
    for _ in range(3):
        scheduler = Scheduler(NO_SPANS)
        scheduler.join("bench-0")
        scheduler.add(1, RunLoop(EMPTY), running=True)
        job = scheduler.lease("bench-0")
        if job is None:
            raise RuntimeError("the scheduler leased no job")
        fitness, components, descriptors = zeros(job.config, 0, job.genomes)
        spent = [0.0, 0.0]
        reply = encode(job.model_copy(update={"ack": Ack(key=job.key, accepted=True)}))
        for _ in range(rounds):
            began = time.perf_counter()
            _, following = decode_result_reply(reply)  # the worker's side
            if following is None:
                raise RuntimeError("the server's reply carried no next job")
            job = following
            delivered = encode(
                Result(
                    key=job.key,
                    worker="bench-0",
                    start=job.start,
                    stop=job.stop,
                    robot_steps_per_s=1e5,
                    seconds=1e-4,
                    want_next=True,
                    fitness=fitness[np.newaxis],
                    components=components[np.newaxis],
                    descriptors=descriptors[np.newaxis],
                )
            )
            middle = time.perf_counter()
            result = decode(delivered, Result)  # the server's side
            ack = scheduler.settle(result)
            scheduler.written(scheduler.take_told())  # the store's part is not timed here
            leased = scheduler.lease(result.worker)
            if leased is None:
                raise RuntimeError("the scheduler leased no next job")
            reply = encode(leased.model_copy(update={"ack": ack}))
            ended = time.perf_counter()
            spent[0] += ended - middle
            spent[1] += middle - began
        if scheduler.totals()["done"] != rounds:
            raise RuntimeError(f"{scheduler.totals()} after {rounds} results")
        costs = [min(best, s / rounds * 1e6) for best, s in zip(costs, spent, strict=True)]
    print(
        f"  per empty job, one process, caches warm: server {costs[0]:.1f} us (read the result, "
        f"settle it: tell and ask; lease, write the job), worker {costs[1]:.1f} us (read the "
        f"job, write the result)"
    )


def _timed_evolve(config: RunConfig, go: threading.Event, seconds: Any) -> None:
    """Child of `bench_capacity`: evolve `config` once `go` is set; its wall time to `seconds`."""
    from evorobotics.evolution import evolve

    evolve(RunConfig(generations=1, seed=99))  # compile the kernels
    seconds.put(None)
    go.wait()
    began = time.perf_counter()
    evolve(config, threads=1)
    seconds.put(time.perf_counter() - began)


def bench_capacity(config: RunConfig) -> None:
    """An evolution on one thread alone and beside a second one: what two processes get from
    this machine's cores (the ceiling of anything that runs beside the evolution, a server
    included)."""
    from evorobotics.evolution import evolve

    ctx = mp.get_context("spawn")
    go, seconds = ctx.Event(), ctx.Queue()
    other = ctx.Process(target=_timed_evolve, args=(config, go, seconds))
    other.start()
    seconds.get(timeout=300)
    evolve(RunConfig(generations=1, seed=99))
    began = time.perf_counter()
    evolve(config, threads=1)
    alone = time.perf_counter() - began
    go.set()
    began = time.perf_counter()
    evolve(config, threads=1)
    beside = time.perf_counter() - began
    other_s = seconds.get(timeout=300)
    other.join(timeout=30)
    pair = (beside + other_s) / 2
    print(
        f"two one-thread evolutions side by side: {pair:.2f} s each against {alone:.2f} s alone: this "
        f"machine runs two at {2 * alone / pair:.2f}x one (load average {os.getloadavg()[0]:.2f})"
    )


def bench_paper(
    workers: int,
    shapes: list[tuple[int, int]],
    repeats: int,
    span_below: float | None,
) -> None:
    """`colony server --workers N` (real processes, REST, zenoh on loopback) vs evolve for each
    (generations, steps) shape on one server, each timed `repeats` times, alternately (figures
    on a shared 2-core VM move by 15 %)."""
    import subprocess
    import sys

    import httpx

    from evorobotics.evolution import evolve

    evolve(RunConfig(generations=1, seed=99))  # compile the kernels
    http, zport = free_port(), free_port()
    url = f"http://127.0.0.1:{http}"
    tick = threading.Event()
    caught_up: tuple[int, int] | None = None
    with tempfile.TemporaryDirectory() as tmp:
        argv = [sys.executable, "-c", "from colony.cli import main; main()", "server"]
        argv += ["--db", f"sqlite:///{Path(tmp) / 'bench.db'}", "--port", str(http)]
        argv += ["--zenoh-listen", f"tcp/127.0.0.1:{zport}", "--workers", str(workers)]
        env = {**os.environ, "COLONY_HOUSEKEEPING_SECONDS": "0.2"}
        if span_below is not None:
            env["COLONY_SPAN_BELOW_SECONDS"] = str(span_below)
        below = span_below
        if below is None:
            below = float(Settings.model_fields["span_below_seconds"].default)
        mode = f"spans below {below * 1e3:g} ms a generation" if below else "slices only"
        server = subprocess.Popen(
            argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        # One client for every call: `httpx.get` builds a client, SSL context included, each
        # time (35 ms of this process's CPU, taken from the run it watches every poll).
        client = httpx.Client(base_url=url, timeout=10)
        try:

            def finish(body: dict[str, object]) -> dict[str, Any]:
                run_id = client.post("/api/runs", json=body).json()["id"]
                while True:  # slow polling: REST calls would compete with the dispatcher
                    run: dict[str, Any] = client.get(f"/api/runs/{run_id}").json()
                    if run["status"] in ("completed", "failed"):
                        return run
                    tick.wait(0.5)

            while True:
                try:
                    if client.get("/healthz", timeout=1).is_success:
                        break
                except httpx.TransportError:
                    tick.wait(0.05)
            # Warm the workers' numba kernels on a throwaway run, as a long-lived worker is:
            # the timed run excludes compilation on both sides.
            finish(RunConfig(generations=1, seed=99).model_dump(mode="json"))
            for generations, steps in shapes:
                config = RunConfig(generations=generations, steps=steps)
                local_s: list[float] = []
                dist_s: list[float] = []
                local_cpu: list[float] = []
                server_cpu: list[float] = []
                workers_cpu: list[float] = []
                shas: set[str] = set()
                worker_pids = children(server.pid)
                for _ in range(repeats):
                    began, cpu = time.perf_counter(), time.process_time()
                    shas.add(evolve(config).best.sha256)
                    local_s.append(time.perf_counter() - began)
                    local_cpu.append(time.process_time() - cpu)
                    server_before = cpu_seconds([server.pid])
                    workers_before = cpu_seconds(worker_pids)
                    run = finish(config.model_dump(mode="json"))
                    server_cpu.append(cpu_seconds([server.pid]) - server_before)
                    workers_cpu.append(cpu_seconds(worker_pids) - workers_before)
                    started = datetime.fromisoformat(run["started_at"])
                    dist_s.append(
                        (datetime.fromisoformat(run["finished_at"]) - started).total_seconds()
                    )
                    shas.add(client.get(f"/api/runs/{run['id']}/best").json()["sha256"])
                same = "identical" if len(shas) == 1 else "DIFFERENT"
                ratio = statistics.median(dist_s) / statistics.median(local_s)
                if caught_up is None and ratio <= 1.0:
                    caught_up = (generations, steps)
                paper = RunConfig()
                name = (
                    "default experiment: "
                    if (generations, steps) == (paper.generations, trial_steps(paper))
                    else ""
                )
                print(
                    f"{name}{generations} generations of {steps} steps (kernels warm, median [min-max] "
                    f"of {repeats}): colony evolve {_spread(local_s)}, colony server --workers "
                    f"{workers} {_spread(dist_s)} (run started to finished, server clock; {mode}), "
                    f"{ratio:.2f}x; best controllers {same}; "
                    f"load average {os.getloadavg()[0]:.2f}"
                )
                on_server, on_workers = (
                    statistics.median(server_cpu),
                    statistics.median(workers_cpu),
                )
                cores = os.cpu_count() or 1
                least = (on_server + on_workers) / cores
                print(
                    "  CPU seconds per run (medians): colony evolve "
                    f"{statistics.median(local_cpu):.2f}; distributed: server {on_server:.2f} "
                    f"(store, dispatch, GA check, REST) + workers {on_workers:.2f} = "
                    f"{on_server + on_workers:.2f}, which {cores} cores cannot run in less than "
                    f"{least:.2f} s ({least / statistics.median(local_s):.2f}x)"
                )
        finally:
            client.close()
            server.terminate()
            server.wait(timeout=60)
    if len(shapes) > 1:
        where = "never" if caught_up is None else f"from {caught_up[1]} steps per trial on"
        print(f"the distributed run is no slower than colony evolve: {where}")


def bench_rank(workers: int, repeats: int) -> None:
    """A stuck robot's `fit` ranking (a paper run's 100 candidates, 40 validation poses x 1,000
    steps, in a calibrated world): asked of a real Dispatcher and Scheduler in this process
    (`Scheduler.rank`) with `workers` worker processes on loopback, against `rank_in_world` in
    this process (what the server ran on a thread before rankings were jobs), alternately; the
    wall time until the ranking is known and this process's CPU (the server's)."""
    from evorobotics.evolution import evolve, rank_in_world, ranking_validation

    config = RunConfig(generations=60, seed=3)
    genomes = evolve(config).genomes[: ranking_validation(config).candidates]
    world = config.world.model_copy(
        update={"whisker_range": (0.03, 0.05, 0.08, 0.05, 0.1), "motor_gain": (1.0, 0.9)}
    )
    ctx = mp.get_context("spawn")
    port = free_port()
    scheduler = Scheduler(Policy(spot_checks=1))
    local: list[tuple[float, float]] = []
    jobs: list[tuple[float, float]] = []
    with Dispatcher(DispatchSettings(listen=(f"tcp/127.0.0.1:{port}",)), scheduler):
        procs, stop = start_workers(ctx, port, workers, empty=False)
        try:
            deadline = time.monotonic() + 120
            while len(scheduler.workers()) < workers:  # spawned interpreters import numba
                if time.monotonic() > deadline:
                    raise TimeoutError("the workers did not join in 120 s")
                stop.wait(0.05)
            scheduler.rank(config, world, genomes[:2]).result(300)  # the workers' kernels warm
            for i in range(repeats):
                moved = world.model_copy(update={"max_speed": 0.3 - 1e-4 * (i + 1)})  # not cached
                began, cpu = time.perf_counter(), time.process_time()
                expected = rank_in_world(config, genomes, moved)
                local.append((time.perf_counter() - began, time.process_time() - cpu))
                began, cpu = time.perf_counter(), time.process_time()
                order, _ = scheduler.rank(config, moved, genomes).result(300)
                jobs.append((time.perf_counter() - began, time.process_time() - cpu))
                if order.tolist() != expected[0].tolist():
                    raise AssertionError("the workers' ranking differs from rank_in_world's")
            logging.getLogger("server.runs.dispatch").setLevel(logging.ERROR)
        finally:
            stop_workers(procs, stop)
    (local_s, local_cpu), (jobs_s, jobs_cpu) = (
        (statistics.median(w for w, _ in runs), statistics.median(c for _, c in runs))
        for runs in (local, jobs)
    )
    print(
        f"a fit ranking ({len(genomes)} candidates, median of {repeats}): in the server "
        f"{local_s:.2f} s wall, {local_cpu:.2f} s of its CPU; as jobs of {workers} workers "
        f"{jobs_s:.2f} s wall ({jobs_s / local_s:.2f}x), {jobs_cpu:.3f} s of the server's CPU "
        f"({jobs_cpu / local_cpu:.3f}x); rankings identical"
    )


def _spread(seconds: list[float]) -> str:
    return f"{statistics.median(seconds):.2f} s [{min(seconds):.2f}-{max(seconds):.2f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--windows", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=5_000, help="per-job cost rounds")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--generations", type=int, default=350)
    parser.add_argument(
        "--steps", type=int, default=trial_steps(RunConfig()), help="(the default trial's)"
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sweep", action="store_true")
    parser.add_argument("--span-below", type=float, default=None)
    parser.add_argument("--only", choices=("throughput", "paper", "rank"), default=None)
    args = parser.parse_args()
    shapes = [(args.generations, args.steps)]
    if args.sweep:  # the same robot-steps, more of them per generation
        robot_steps = args.generations * args.steps
        shapes += [
            (max(1, robot_steps // s), s) for s in (100, 200, 400, 800, 1600) if s > args.steps
        ]
    if args.only in (None, "throughput"):
        bench_throughput(args.seconds, args.workers, args.windows)
        bench_codec(args.rounds)
    if args.only in (None, "rank"):
        bench_rank(args.workers, args.repeats)
    if args.only in (None, "paper"):
        bench_capacity(RunConfig(generations=args.generations, steps=args.steps))
        bench_paper(args.workers, shapes, args.repeats, args.span_below)


if __name__ == "__main__":
    main()
