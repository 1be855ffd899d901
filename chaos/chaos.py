"""Chaos suite (`make chaos`): a run disturbed by real failures must end as if undisturbed.

Real processes on loopback: `colony server` on an SQLite file, `colony worker`s, and virtual
robots (`colony agent --emulate`), all authenticated with a lab from `colony lab init --tls`:
zenoh over TLS with a user per role (one worker user, its processes named `chaos.wN`; one per
robot) and the router's access control, the REST token, and robots verifying signed
replacements with the pinned server key. During the run, on a schedule drawn from a seeded generator
(reproducible with `--chaos-seed`): a random worker the server lists as serving is SIGKILLed
every few seconds (and a fresh one started), the server is SIGKILLed and restarted twice (which also cuts every robot's
link), and the store refuses writes for a while (an exclusive SQLite lock held by this script:
root ignores file modes and the server's pooled connections keep the mode they opened with, so
the lock is the outside mechanism that makes every write of the live server fail). The run must
pause with a clear error, lose no committed generation, resume when asked, and end with the
best controller of `evorobotics.evolution.evolve` for the same config, bit for bit.

Prints a report: jobs requeued and duplicates dropped (from /metrics, summed over the server's
lives), generations lost, robots' trace gaps.
"""

from __future__ import annotations

import argparse
import os
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from evorobotics.evolution import evolve
from schemas.run import RunConfig

COLONY = [sys.executable, "-c", "from colony.cli import main; main()"]
WORKER_USER = "chaos"
"""The lab's worker user: every worker process runs under it as `chaos.wN`."""
TICK = threading.Event()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def wait_until(predicate: Callable[[], bool], what: str, timeout: float = 120.0) -> None:
    """Poll REST state (no event announces it) until a deadline."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        TICK.wait(0.1)


def read_env(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line)


class Lab:
    """Server, workers and robots as subprocesses with the credentials of a lab made by
    `colony lab init`, logs in a temp dir; all killed at the end."""

    def __init__(self, tmp: Path, robots: list[str]) -> None:
        self.tmp = tmp
        self.db = tmp / "colony.db"
        self.http, self.zenoh = free_port(), free_port()
        self.url = f"http://127.0.0.1:{self.http}"
        creds = tmp / "lab"
        init = [*COLONY, "lab", "init", str(creds), "--server-host", "127.0.0.1", "--tls"]
        init += ["--port", str(self.zenoh), "--worker", WORKER_USER]
        for robot in robots:
            init += ["--robot", robot]
        subprocess.run(init, check=True, stdout=subprocess.DEVNULL)
        self.server_env = read_env(creds / "server.env")
        self.worker_env = read_env(creds / "workers" / f"{WORKER_USER}.env")
        self.robot_envs = {robot: read_env(creds / "robots" / f"{robot}.env") for robot in robots}
        self.endpoint = self.worker_env["COLONY_CONNECT"]
        self.server: subprocess.Popen[bytes] | None = None
        self.workers: dict[str, subprocess.Popen[bytes]] = {}
        self.procs: list[subprocess.Popen[bytes]] = []
        token = self.server_env["COLONY_API_TOKEN"]
        self.client = httpx.Client(
            base_url=self.url, headers={"Authorization": f"Bearer {token}"}, timeout=10
        )

    def spawn(self, argv: list[str], log: str, env: dict[str, str] | None = None) -> Any:
        with (self.tmp / f"{log}.log").open("ab") as out:
            proc = subprocess.Popen(
                argv,
                env={**os.environ, **(env or {})},
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        self.procs.append(proc)
        return proc

    def start_server(self) -> None:
        argv = [*COLONY, "server", "--db", f"sqlite:///{self.db}", "--port", str(self.http)]
        # the lab's server listens on every interface: this script keeps it on loopback
        argv += ["--host", "127.0.0.1", "--zenoh-listen", self.endpoint, "--workers", "0"]
        env = {**self.server_env, "COLONY_HOUSEKEEPING_SECONDS": "0.5"}
        self.server = self.spawn(argv, "server", env)
        wait_until(self.healthy, "server health", 60)

    def healthy(self) -> bool:
        assert self.server is not None
        if self.server.poll() is not None:
            raise RuntimeError(f"colony server exited with {self.server.returncode}")
        try:
            return self.client.get("/healthz", timeout=1).is_success
        except httpx.TransportError:
            return False

    def kill_server(self) -> dict[str, float]:
        """SIGKILL the server; returns its counters just before."""
        counters = self.metrics()
        assert self.server is not None
        self.server.kill()
        self.server.wait(timeout=30)
        return counters

    def start_worker(self, serial: int) -> None:
        name = f"{WORKER_USER}.w{serial}"
        argv = [*COLONY, "worker", "--name", name]
        self.workers[name] = self.spawn(argv, name, self.worker_env)

    def start_robot(self, robot: str, seed: int) -> None:
        argv = [*COLONY, "agent", "--emulate", "--seed", str(seed)]
        argv += ["--state-dir", str(self.tmp / robot)]
        self.spawn(argv, robot, self.robot_envs[robot])

    def serving(self) -> list[str]:
        """This script's live workers the server lists as idle or busy: killing one that is
        still starting (a loaded machine takes seconds to import) would test nothing."""
        listed = self.client.get("/api/workers").json()
        joined = {w["name"] for w in listed if w["state"] in ("idle", "busy")}
        return sorted(name for name in self.workers if name in joined)

    def metrics(self) -> dict[str, float]:
        text = self.client.get("/metrics").text
        out: dict[str, float] = {}
        for line in text.splitlines():
            if line.startswith("colony_") and " " in line:
                name, value = line.rsplit(" ", 1)
                out[name] = float(value)
        return out

    def run(self, run_id: int) -> dict[str, Any]:
        run: dict[str, Any] = self.client.get(f"/api/runs/{run_id}").json()
        return run

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
        for proc in self.procs:
            proc.wait(timeout=30)
        self.client.close()


def trace_gaps(lab: Lab, robot: str) -> tuple[int, int]:
    """(samples stored, samples missing between the first and last stored step of each boot)."""
    samples = lab.client.get(f"/api/robots/{robot}/traces", params={"limit": 100_000}).json()
    by_boot: dict[int, list[int]] = {}
    for sample in samples["samples"]:
        by_boot.setdefault(sample["boot"], []).append(sample["step"])
    gaps = sum(max(s) - min(s) + 1 - len(set(s)) for s in by_boot.values())
    return sum(len(s) for s in by_boot.values()), gaps


def committed(lab: Lab, run_id: int) -> int:
    """Generations the store holds for the run, read from the file itself (the REST view may
    be one generation ahead of the store: the write is deferred)."""
    with sqlite3.connect(f"file:{lab.db}?mode=ro", uri=True, timeout=30) as db:
        row = db.execute("SELECT count(*) FROM generations WHERE run_id = ?", (run_id,))
        return int(row.fetchone()[0])


def chaos(args: argparse.Namespace) -> dict[str, Any]:
    config = RunConfig(
        population=args.population,
        job_size=args.job_size,
        generations=args.generations,
        steps=args.steps,
        seed=args.seed,
    )
    began = time.monotonic()
    expected = evolve(config).best.sha256
    print(f"evolve (undisturbed): best {expected[:16]} in {time.monotonic() - began:.1f} s")
    schedule = np.random.default_rng(args.chaos_seed)
    g = args.generations
    first = int(schedule.integers(g // 8, g // 4))
    server_kills = [first, first + int(schedule.integers(g // 8, g // 4))]
    refuse_at = int(schedule.integers(g // 2 + 2, 3 * g // 4))
    report: dict[str, Any] = {"server_kills_at": list(server_kills), "refuse_at": refuse_at}
    totals = {"requeued": 0.0, "duplicates_dropped": 0.0}
    robots = [f"chaos-{i}" for i in range(args.robots)]
    lab = Lab(Path(tempfile.mkdtemp(prefix="colony-chaos-")), robots)
    print(f"logs in {lab.tmp}; schedule: server kills at generations {server_kills}, "
          f"store refuses writes from generation {refuse_at}")  # fmt: skip
    worker_kills = 0
    lost = 0
    try:
        lab.start_server()
        serial = iter(range(10**6))
        for _ in range(args.workers):
            lab.start_worker(next(serial))
        for i, robot in enumerate(robots):
            lab.start_robot(robot, i)
        run_id = int(lab.client.post("/api/runs", json=config.model_dump(mode="json")).json()["id"])
        next_kill = time.monotonic() + float(schedule.uniform(2, 5))
        refused = False
        high = 0
        while (run := lab.run(run_id))["status"] not in ("completed", "failed"):
            gen = int(run["generation"])
            stored = committed(lab, run_id)
            lost += max(0, high - stored)  # a committed generation never disappears
            high = max(high, stored)
            if server_kills and gen >= server_kills[0]:
                server_kills.pop(0)
                before = committed(lab, run_id)
                counters = lab.kill_server()
                for name in totals:
                    totals[name] += counters.get(f"colony_jobs_{name}_total", 0.0)
                report.setdefault("server_killed_at", []).append(gen)
                print(f"  gen {gen}: server SIGKILLed (store held {before}); restarting")
                lab.start_server()
                after = committed(lab, run_id)
                lost += max(0, before - after)
                print(f"  server back, store holds generation {after}")
            elif not refused and gen >= refuse_at:
                refused = True
                report.update(refuse_writes(lab, run_id, args.refuse))
            elif time.monotonic() >= next_kill and (serving := lab.serving()):
                name = str(schedule.choice(serving))
                lab.workers.pop(name).kill()
                lab.start_worker(next(serial))
                worker_kills += 1
                print(f"  gen {gen}: worker {name} SIGKILLed, a fresh one started")
                next_kill = time.monotonic() + float(schedule.uniform(2, 5))
            TICK.wait(0.2)
        run = lab.run(run_id)
        best = lab.client.get(f"/api/runs/{run_id}/best").json()
        counters = lab.metrics()
        for name in totals:
            totals[name] += counters.get(f"colony_jobs_{name}_total", 0.0)
        TICK.wait(3.0)  # robots deliver their last batches (one a second)
        gaps = {robot: trace_gaps(lab, robot) for robot in robots}
        report.update(
            status=run["status"],
            error=run["error"],
            evaluations=run["evaluations"],
            expected_evaluations=config.population * config.generations,
            identical=best.get("sha256") == expected,
            worker_kills=worker_kills,
            server_kills=2,
            jobs_requeued=int(totals["requeued"]),
            duplicates_dropped=int(totals["duplicates_dropped"]),
            generations_lost=lost + max(0, config.generations - committed(lab, run_id)),
            robot_samples={r: n for r, (n, _) in gaps.items()},
            trace_gaps=sum(gap for _, gap in gaps.values()),
            seconds=round(time.monotonic() - began, 1),
        )
    finally:
        lab.close()
    return report


def refuse_writes(lab: Lab, run_id: int, seconds: float) -> dict[str, Any]:
    """Hold an exclusive SQLite lock for `seconds`: the run must stop evolving (at most the one
    generation in flight, or one span message, ahead of the store), then, once the store takes
    the writes again, be paused with the write error; resume it. Returns how far the stored
    run got while refused, how far once writable, and whether it paused (a run that ended
    instead evolved on in memory while the store refused: a failed check)."""
    lock = sqlite3.connect(lab.db, timeout=30, isolation_level=None)
    try:
        lock.execute("BEGIN EXCLUSIVE")
        start = int(lab.run(run_id)["generation"])
        print(f"  gen {start}: store refuses writes (exclusive lock) for {seconds:.0f} s")
        TICK.wait(seconds)
        reached = int(lab.run(run_id)["generation"])
        print(f"  while refused the run went from generation {start} to {reached}")
    finally:
        lock.execute("ROLLBACK")
        lock.close()
    wait_until(lambda: lab.run(run_id)["status"] != "running", "the run to pause", 60)
    run = lab.run(run_id)
    refused = {
        "generations_while_refused": reached - start,
        "generations_ahead_of_store": int(run["generation"]) - start,
        "paused_after_refusal": run["status"] == "paused",
    }
    if run["status"] != "paused":
        print(
            f"  store writable: run {run['status']} at generation {run['generation']} instead "
            f"of pausing: it evolved on in memory while the store refused writes"
        )
        return refused
    print(f"  store writable: run paused at generation {run['generation']}, {run['error']!r}")
    if not str(run["error"] or "").startswith("database write failed"):
        raise RuntimeError(f"paused without the write error: {run['error']!r}")
    resumed = lab.client.post(f"/api/runs/{run_id}/resume")
    if resumed.status_code == 409 and lab.run(run_id)["status"] == "completed":
        # the generations told before the pause took effect (a span's last message may carry
        # the run's end) were written with the paused one: nothing is left to resume
        print(f"  completed from generations told before the pause: {resumed.json()['detail']}")
        return refused
    resumed.raise_for_status()
    print(f"  resumed: status {lab.run(run_id)['status']}")
    return refused


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--population", type=int, default=40)
    parser.add_argument("--job-size", type=int, default=5)
    parser.add_argument("--generations", type=int, default=120)
    parser.add_argument("--steps", type=int, default=4000, help="long enough for the schedule")
    parser.add_argument("--seed", type=int, default=0, help="the run's seed")
    parser.add_argument("--chaos-seed", type=int, default=1, help="seed of the chaos schedule")
    parser.add_argument("--workers", type=int, default=3)
    parser.add_argument("--robots", type=int, default=4)
    parser.add_argument("--refuse", type=float, default=20.0, help="seconds the store refuses")
    args = parser.parse_args()
    report = chaos(args)
    print("\nchaos report")
    for key, value in report.items():
        print(f"  {key}: {value}")
    last = report["expected_evaluations"] // args.population - 1
    mid_run = report["worker_kills"] > 0 and all(
        g < last for g in report.get("server_killed_at", [last])
    )
    if not mid_run:
        print("the run ended before the chaos it was to survive: lengthen it (--steps)")
    ok = (
        mid_run
        and report["status"] == "completed"
        and report.get("paused_after_refusal", False)
        and report["identical"]
        and report["generations_lost"] == 0
        and report["trace_gaps"] == 0
        and report["evaluations"] == report["expected_evaluations"]
    )
    print("PASS" if ok else "FAIL")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
