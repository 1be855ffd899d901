"""A study through `colony server` against sequential `colony evolve`, and how many workers one
server keeps busy (prints figures; no assertions).

1. A study of `--seeds` runs of one condition (the paper's experiment by default: RunConfig's
   defaults, seeds 0..N-1) on `colony server --workers 2` (a subprocess: SQLite in a temp dir,
   REST and zenoh on loopback) against the same configs and seeds as `colony evolve --out DIR`
   processes one after another, alternately `--repeats` times in one run. The study's time is
   the server's clock from the study's creation to its last run's completion: the champions'
   exploration figures, which the workers compute afterwards (report jobs), are not awaited.
   The champions' sha256 must be the same on both sides.
2. The server process's CPU (/proc/PID/stat utime + stime, not its worker children) and its
   local workers' CPU, sampled while the study's runs evolve (from 10 % of their generations
   until the first run reaches its last one: no run starts, or is validated, in that window),
   per generation; the server's and the workers' CPU per run (all of it from creation to the
   champions' exploration figures, over the runs) and the server's share of the study's CPU
   (server / (server + workers)). A study of `--big-seeds` runs with ten times the trial
   length (`steps` x 10) gives the same at that scale. N = workers' CPU per generation /
   server CPU per generation: how many workers one server keeps busy (docs/deployment.md,
   "Sizing a lab"); and the GA's ask and tell alone per generation, timed in this process,
   which the server replays for every generation: the N no replaying server passes.

    .venv/bin/python bench/study.py [--seeds 8] [--repeats 3] [--generations 350]
        [--big-seeds 4] [--big-generations 20] [--quick]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import socket
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from _procs import children, cpu_seconds

from evorobotics.evaluate import trial_steps
from evorobotics.evolution import RunLoop
from schemas.run import RunConfig

QUICK = {
    "population": 8,
    "generations": 3,
    "steps": 20,
    "validation": {"poses": 2, "steps": 20, "candidates": 2},
}
"""`--quick`'s base config: a tiny population, few short trials, a tiny validation set."""
TICK_S = 0.5
"""How often the study's progress is read (from its SQLite file: no request to the server)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class StudyFigures:
    """One study on the server: its wall time, champions, and CPU over its runs' middle."""

    wall_s: float
    shas: dict[int, str | None]
    """seed -> champion sha256"""
    generations: int
    server_per_generation_s: float
    workers_per_generation_s: float
    server_per_run_s: float
    workers_per_run_s: float


class Server:
    """`colony server --workers N` in a subprocess on a fresh SQLite file and free ports."""

    def __init__(self, tmp: Path, workers: int) -> None:
        self.db = tmp / "bench.db"
        http, zport = free_port(), free_port()
        argv = [sys.executable, "-c", "from colony.cli import main; main()", "server"]
        argv += ["--db", f"sqlite:///{self.db}", "--port", str(http)]
        argv += ["--zenoh-listen", f"tcp/127.0.0.1:{zport}", "--workers", str(workers)]
        self.process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{http}", timeout=30)
        self.tick = threading.Event()
        deadline = time.monotonic() + 120
        while True:
            with contextlib.suppress(httpx.TransportError):
                if self.client.get("/healthz", timeout=1).is_success:
                    break
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("colony server did not start")
            self.tick.wait(0.1)
        self.workers = children(self.process.pid)
        self.studies = 0

    def close(self) -> None:
        self.client.close()
        self.process.terminate()
        self.process.wait(timeout=60)

    def _runs(self, study: int) -> list[tuple[int, str, int, str | None, str | None]]:
        """(seed, status, generation, champion sha256, finished_at) of the study's runs."""
        with contextlib.closing(sqlite3.connect(f"file:{self.db}?mode=ro", uri=True)) as db:
            db.execute("PRAGMA busy_timeout = 5000")
            return db.execute(
                "SELECT seed, status, generation, champion_sha256, finished_at FROM runs "
                "WHERE study_id = ?",
                (study,),
            ).fetchall()

    def study(self, base: dict[str, Any], seeds: list[int]) -> StudyFigures:
        """Run a one-condition study of `base` over `seeds` to the end, exploration included."""
        self.studies += 1
        per_run = RunConfig.model_validate(base).generations
        generations = per_run * len(seeds)
        server0, workers0 = cpu_seconds([self.process.pid]), cpu_seconds(self.workers)
        body = {"name": f"bench-{self.studies}", "base": base, "seeds": seeds}
        created = self.client.post("/api/studies", json=body)
        created.raise_for_status()
        study = created.json()
        samples: list[tuple[int, float, float]] = []  # generations done, server, workers CPU
        while True:
            runs = self._runs(study["id"])
            done = sum(r[2] for r in runs)
            if not any(r[2] >= per_run - 1 for r in runs):  # no run at its end (validation)
                samples.append((done, cpu_seconds([self.process.pid]), cpu_seconds(self.workers)))
            if any(r[1] in ("failed", "cancelled") for r in runs):
                raise RuntimeError(f"a run of study {study['id']} did not complete")
            if all(r[1] == "completed" for r in runs):
                break
            self.tick.wait(TICK_S)
        began = datetime.fromisoformat(study["created_at"]).replace(tzinfo=None)
        ended = max(datetime.fromisoformat(str(r[4])).replace(tzinfo=None) for r in runs)
        self._explored(study["id"])
        server_end, workers_end = cpu_seconds([self.process.pid]), cpu_seconds(self.workers)
        middle = [s for s in samples if s[0] >= 0.1 * generations]
        window = middle if len(middle) > 1 else samples or [(0, 0.0, 0.0)]
        first, last = window[0], window[-1]
        counted = max(1, last[0] - first[0])
        return StudyFigures(
            wall_s=(ended - began).total_seconds(),
            shas={int(r[0]): r[3] for r in runs},
            generations=counted,
            server_per_generation_s=(last[1] - first[1]) / counted,
            workers_per_generation_s=(last[2] - first[2]) / counted,
            server_per_run_s=(server_end - server0) / len(seeds),
            workers_per_run_s=(workers_end - workers0) / len(seeds),
        )

    def _explored(self, study: int) -> None:
        """Wait until every champion's exploration figures are known (at most 300 s)."""
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            runs = self.client.get(f"/api/studies/{study}").json()["runs"]
            if all(r["metrics"].get("coverage") is not None for r in runs):
                return
            self.tick.wait(1.0)


def sequential(
    base: dict[str, Any], seeds: list[int], tmp: Path
) -> tuple[float, float, dict[int, str]]:
    """`colony evolve --config FILE --out DIR` per seed, one after another: wall time, the
    evolution's share of it as each process reports it (no start, imports or plots), shas."""
    shas: dict[int, str] = {}
    evolution = 0.0
    began = time.perf_counter()
    for seed in seeds:
        out = Path(tempfile.mkdtemp(dir=tmp))
        config = out / "in.json"
        config.write_text(RunConfig.model_validate({**base, "seed": seed}).model_dump_json())
        argv = [sys.executable, "-c", "from colony.cli import main; main()", "evolve"]
        done = subprocess.run(
            [*argv, "--config", str(config), "--out", str(out)],
            check=True,
            capture_output=True,
            text=True,
        )
        found = re.search(r"\(evolution ([0-9.]+) s", done.stdout)
        if found is None:
            raise RuntimeError(f"colony evolve printed no evolution time: {done.stdout[-300:]}")
        evolution += float(found[1])
        shas[seed] = json.loads((out / "best.json").read_text())["sha256"]
    return time.perf_counter() - began, evolution, shas


def _spread(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} [{min(values):.2f}-{max(values):.2f}]"


def sizing(label: str, figures: list[StudyFigures], config: RunConfig) -> None:
    """Print the inputs and N = workers' CPU per generation / server CPU per generation."""
    server = statistics.median(f.server_per_generation_s for f in figures)
    workers = statistics.median(f.workers_per_generation_s for f in figures)
    per_run = statistics.median(f.server_per_run_s for f in figures)
    workers_run = statistics.median(f.workers_per_run_s for f in figures)
    print(
        f"  {label}: {config.population} x {config.trials} trials x {trial_steps(config)} steps "
        f"a generation; CPU per generation over {figures[0].generations} generations in the "
        f"middle of the runs: server {server * 1e3:.2f} ms, workers {workers * 1e3:.1f} ms; "
        f"CPU per run ({config.generations} generations, champion validation and exploration "
        f"included): server {per_run:.2f} s, workers {workers_run:.2f} s"
    )
    share = per_run / (per_run + workers_run) if per_run + workers_run > 0 else 0.0
    print(f"  the server's share of the study's CPU: {100 * share:.1f} %")
    busy = workers / server if server > 0 else float("inf")
    print(f"  one server keeps about {busy:.0f} workers busy at {label}")
    replay = replay_seconds(config)
    print(
        f"  the GA's ask and tell alone, which the server replays for every generation: "
        f"{replay * 1e3:.2f} ms a generation in this process, so at most about "
        f"{workers / replay:.0f} workers however lean the rest"
    )


def replay_seconds(config: RunConfig, generations: int = 300) -> float:
    """CPU seconds of one generation's `RunLoop.ask` and `tell` (random fitness): what the
    server computes for every generation to check a span's genomes and store checkpoints."""
    loop = RunLoop(config.model_copy(update={"generations": generations + 1}))
    fitness = np.random.default_rng(0).random((generations, config.population))
    started = time.process_time()
    for row in fitness:
        loop.ask()
        loop.tell(row)
    return (time.process_time() - started) / generations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seeds", type=int, default=8, help="runs of the study: seeds 0..N-1")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2, help="colony server --workers")
    parser.add_argument("--generations", type=int, default=None, help="[the paper's 350]")
    parser.add_argument("--big-seeds", type=int, default=4, help="runs of the 10x-steps study")
    parser.add_argument("--big-generations", type=int, default=20)
    parser.add_argument("--quick", action="store_true", help="a tiny config (the test's)")
    args = parser.parse_args()
    base: dict[str, Any] = dict(QUICK) if args.quick else {}
    if args.generations is not None:
        base["generations"] = args.generations
    paper = RunConfig.model_validate(base)
    big = {**base, "steps": 10 * trial_steps(paper), "generations": args.big_generations}
    seeds = list(range(args.seeds))
    with tempfile.TemporaryDirectory() as name:
        tmp = Path(name)
        server = Server(tmp, args.workers)
        try:
            # the workers compile their kernels on a throwaway study, as long-lived ones are
            server.study({**base, "generations": 1}, [99])
            ratios: list[float] = []
            evolution_ratios: list[float] = []
            studies: list[StudyFigures] = []
            identical = True
            for repeat in range(args.repeats):
                local_s, evolution_s, local = sequential(base, seeds, tmp)
                figures = server.study(base, seeds)
                studies.append(figures)
                identical = identical and figures.shas == local
                ratios.append(figures.wall_s / local_s)
                evolution_ratios.append(figures.wall_s / evolution_s)
                print(
                    f"repeat {repeat + 1}/{args.repeats}: study of {len(seeds)} runs on colony "
                    f"server --workers {args.workers} {figures.wall_s:.2f} s (created to last run "
                    f"completed, server clock; the exploration figures computed after are not "
                    f"awaited), {len(seeds)} sequential colony evolve {local_s:.2f} s (their "
                    f"evolution alone {evolution_s:.2f} s), ratio {ratios[-1]:.2f} "
                    f"({evolution_ratios[-1]:.2f} against the evolution alone); "
                    f"load average {os.getloadavg()[0]:.2f}",
                    flush=True,
                )
            print(
                f"median ratio server / sequential: {statistics.median(ratios):.2f} "
                f"(0.5 is perfect on 2 cores; {_spread(ratios)} over {args.repeats} repeats); "
                f"against the evolution alone, without each process's start, imports and plots: "
                f"{statistics.median(evolution_ratios):.2f}"
            )
            print(f"champions identical: {'yes' if identical else 'no'}")
            print("sizing (N = workers' CPU per generation / server CPU per generation):")
            sizing("the paper's scale", studies, paper)
            bigger = server.study(big, list(range(args.big_seeds)))
            sizing("10x the trial length", [bigger], RunConfig.model_validate(big))
        finally:
            server.close()


if __name__ == "__main__":
    main()
