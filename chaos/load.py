"""Load test (`make load`): 64 virtual robots, 4 workers evolving, 50 status queries a second.

A real `colony server` (SQLite file, zenoh over TLS on loopback) and 4 `colony worker` processes
run an evolution (a new run whenever one ends); 64 virtual EvBots (BasicX emulator on a pty + driver +
agent with a random paper-best controller, each) run in `--procs` spawned processes, as in
bench/colony.py; every process authenticates with a lab from `colony lab init --tls` (a user per
robot, one worker user, the REST token; robots verify signed pushes with the pinned key); a thread issues 50 GET/s alternating /api/colony and /api/robots. Reports: trace
samples stored and gaps (steps missing below each robot's highest stored step: must be 0),
status latency p50/p99/max, generations evolved, and the RSS of every process sampled every
`--sample-seconds` (a series: flat, bounded growth or a leak are told apart by its shape).

`--tracemalloc` runs the server under tracemalloc (25 frames) and writes, every
`--sample-seconds`, the top allocation sites by line grown since the first snapshot to
`tracemalloc.txt` in the logs directory (slow: for hunting growth, not for figures).

    .venv/bin/python chaos/load.py --seconds 300
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from evorobotics.document import ControllerDocument
from robot_agent.agent import Agent, AgentSettings
from robot_agent.driver import BasicXDriver
from robot_agent.emulator import BasicXEmulator
from robot_agent.sim_body import SimBody
from schemas.network import NetworkSpec
from schemas.security import ZenohClientAuth

COLONY = [sys.executable, "-c", "from colony.cli import main; main()"]
WORKER_USER = "load"
"""The lab's worker user: the worker processes run under it as `load.wN`."""
RUN = {"population": 40, "job_size": 5, "generations": 200, "steps": 400}
TRACED_SERVER = """
import os, sys, threading, tracemalloc
sys.argv = ["colony", *sys.argv[1:]]
from colony.cli import main
import server.app, server.runs.dispatch, server.runs.lifecycle, server.robots.service  # imported before tracing
inboxes = []  # (name, queue) of the zenoh callbacks' queues: their depth is reported too
def keep(cls, method):
    original = getattr(cls, method)
    def wrapped(self, *a, **k):
        result = original(self, *a, **k)
        inboxes.append((cls.__name__, self._inbox))
        return result
    setattr(cls, method, wrapped)
keep(server.robots.service.RobotService, "start")
keep(server.runs.dispatch.Dispatcher, "__init__")
tracemalloc.start(int(os.environ.get("LOAD_TRACEMALLOC_FRAMES", "1")))
out, every = os.environ["LOAD_TRACEMALLOC"], float(os.environ["LOAD_TRACEMALLOC_EVERY"])
def dump():
    base, halt, k = tracemalloc.take_snapshot(), threading.Event(), 0
    while not halt.wait(every):
        k += 1
        snap = tracemalloc.take_snapshot()
        top = snap.compare_to(base, "traceback" if FRAMES > 1 else "lineno")[:25]
        size = sum(s.size for s in snap.statistics("filename")) / 2**20
        with open(out, "a") as f:
            depth = ", ".join(f"{n} inbox {q.qsize()}" for n, q in inboxes)
            print(f"== snapshot {k} at {k * every:.0f} s: traced {size:.1f} MiB; {depth}", file=f)
            for stat in top:
                print(f"  {stat}", file=f)
                if FRAMES > 1:
                    print("    " + "\\n    ".join(stat.traceback.format()[-2 * FRAMES:]), file=f)
FRAMES = tracemalloc.get_traceback_limit()
threading.Thread(target=dump, daemon=True).start()
main()
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rss_mib(pid: int, field: str = "VmRSS") -> float:
    """Resident set size of `pid` in MiB (0 once it is gone); `field="RssShmem"`: the part of
    it in shared memory (zenoh's shared-memory pools, mapped by both ends of a link)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) / 1024
    except FileNotFoundError:
        pass
    return 0.0


def read_env(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line)


def robots_process(first: int, count: int, lab: str, state: str, halt: Any, out: Any) -> None:
    """Run `count` virtual robots with their credentials in the lab directory `lab` until
    `halt`; report produced/unsent/dropped on `out`."""
    sys.setswitchinterval(0.001)  # many threads share one GIL: hand it over sooner
    spec = NetworkSpec()
    rigs = []
    for i in range(first, first + count):
        doc = ControllerDocument(spec, np.random.default_rng(i).uniform(-1, 1, spec.weight_count))
        state_dir = Path(state) / f"r{i}"
        state_dir.mkdir(parents=True)
        (state_dir / "controller.json").write_text(doc.to_json())
        emulator = BasicXEmulator(SimBody.create("paper", seed=0, index=i)).start()
        driver = BasicXDriver.open(emulator.port_path)
        env = read_env(Path(lab) / "robots" / f"load-{i}.env")
        settings = AgentSettings(
            f"load-{i}",
            connect=(env["COLONY_CONNECT"],),
            state_dir=state_dir,
            server_key=Path(env["COLONY_SERVER_PUBLIC_KEY"]).read_bytes(),
            require_signature=True,
            auth=ZenohClientAuth(
                env["COLONY_ZENOH_USER"],
                env["COLONY_ZENOH_PASSWORD"],
                Path(env["COLONY_ZENOH_ROOT_CA"]),
            ),
        )
        rigs.append((emulator, driver, Agent(settings, driver).start()))
    for _, _, agent in rigs:
        agent.connected.wait(60)
    halt.wait()
    deadline = time.monotonic() + 15  # let the last batches go out
    for _, _, agent in rigs:
        agent.wait_for(lambda a=agent: a.buffered() < 20, max(0.0, deadline - time.monotonic()))  # type: ignore[misc]
    for emulator, driver, agent in rigs:
        agent.stop()
        driver.close()
        emulator.stop()
    out.put(
        {
            "produced": sum(agent.steps for _, _, agent in rigs),
            "unsent": sum(agent.buffered() for _, _, agent in rigs),
            "dropped": sum(agent.dropped for _, _, agent in rigs),
        }
    )


QUERIERS = 8
"""Concurrent status clients sharing the query rate."""


def query_loop(url: str, rate: float, halt: threading.Event, latencies: list[float]) -> None:
    """`rate` GETs a second on a deadline schedule, alternating the two status endpoints."""
    paths = ("/api/colony", "/api/robots")
    with httpx.Client(base_url=url, timeout=10) as client:
        due = time.monotonic()
        k = 0
        while not halt.is_set():
            began = time.perf_counter()
            client.get(paths[k % 2]).raise_for_status()
            latencies.append(time.perf_counter() - began)
            k += 1
            due += 1.0 / rate
            halt.wait(max(0.0, due - time.monotonic()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seconds", type=float, default=300.0)
    parser.add_argument("--robots", type=int, default=64)
    parser.add_argument("--procs", type=int, default=4, help="processes hosting the robots")
    parser.add_argument("--workers", type=int, default=4)
    parser.add_argument("--rate", type=float, default=50.0, help="status queries per second")
    parser.add_argument("--sample-seconds", type=float, default=5.0, help="RSS sampling period")
    parser.add_argument("--tracemalloc", action="store_true", help="server growth by line")
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="colony-load-"))
    db = tmp / "colony.db"
    http, port, local = free_port(), free_port(), free_port()
    lab = tmp / "lab"
    init = [*COLONY, "lab", "init", str(lab), "--server-host", "127.0.0.1", "--tls"]
    init += ["--port", str(port), "--worker", WORKER_USER]
    for i in range(args.robots):
        init += ["--robot", f"load-{i}"]
    subprocess.run(init, check=True, stdout=subprocess.DEVNULL)
    server_env = read_env(lab / "server.env")
    worker_env = read_env(lab / "workers" / f"{WORKER_USER}.env")
    url, endpoint = f"http://127.0.0.1:{http}", worker_env["COLONY_CONNECT"]
    procs: dict[str, subprocess.Popen[bytes]] = {}

    def spawn(name: str, argv: list[str], env: dict[str, str]) -> None:
        with (tmp / f"{name}.log").open("ab") as log:
            procs[name] = subprocess.Popen(
                argv,
                env={**os.environ, **env},
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
            )

    ctx = mp.get_context("spawn")
    robot_procs: list[Any] = []
    try:
        server = [sys.executable, "-c", TRACED_SERVER] if args.tracemalloc else COLONY
        os.environ["LOAD_TRACEMALLOC"] = str(tmp / "tracemalloc.txt")
        os.environ["LOAD_TRACEMALLOC_EVERY"] = str(args.sample_seconds)
        argv = [*server, "server", "--db", f"sqlite:///{db}", "--port", str(http)]
        # the lab's server listens on every interface: this script keeps it on loopback (its
        # local workers, user `local` of the lab, connect over tcp as the lab's do)
        argv += ["--host", "127.0.0.1", "--zenoh-listen", endpoint]
        spawn("server", [*argv, "--zenoh-listen", f"tcp/127.0.0.1:{local}"], server_env)
        token = server_env["COLONY_API_TOKEN"]
        client = httpx.Client(
            base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=10
        )
        deadline = time.monotonic() + (300 if args.tracemalloc else 60)
        while True:
            try:
                if client.get("/healthz").is_success:
                    break
            except httpx.TransportError:
                pass
            if procs["server"].poll() is not None:
                raise RuntimeError(f"server exited: see {tmp}/server.log")
            if time.monotonic() > deadline:
                raise TimeoutError("server did not start")
            threading.Event().wait(0.1)
        for w in range(args.workers):
            spawn(f"worker{w}", [*COLONY, "worker", "--name", f"{WORKER_USER}.w{w}"], worker_env)
        halt, out = ctx.Event(), ctx.Queue()
        shares = [
            args.robots // args.procs + (k < args.robots % args.procs) for k in range(args.procs)
        ]
        first = 0
        for k, count in enumerate(shares):
            p = ctx.Process(
                target=robots_process,
                args=(first, count, str(lab), f"{tmp}/p{k}", halt, out),
            )
            p.start()
            robot_procs.append(p)
            first += count
        run_ids = [int(client.post("/api/runs", json=RUN).json()["id"])]
        wait_online = time.monotonic() + 120
        while sum(r["online"] for r in client.get("/api/robots").json()) < args.robots:
            if time.monotonic() > wait_online:
                raise TimeoutError("robots did not all come online")
            threading.Event().wait(0.5)
        pids = {name: p.pid for name, p in procs.items()}
        pids.update({f"robots{k}": p.pid for k, p in enumerate(robot_procs)})
        series: dict[str, list[float]] = {name: [rss_mib(pid)] for name, pid in pids.items()}
        shmem = {name: rss_mib(pid, "RssShmem") for name, pid in pids.items()}
        print(f"logs in {tmp}; {args.robots} robots online; load for {args.seconds:.0f} s")
        stop_queries = threading.Event()
        latencies: list[float] = []
        # several clients, each on its own deadline schedule: a slow answer delays one client,
        # not the offered rate (one sequential client reached only ~25/s under full CPU load)
        queriers = [
            threading.Thread(
                target=query_loop, args=(url, args.rate / QUERIERS, stop_queries, latencies)
            )
            for _ in range(QUERIERS)
        ]
        began = time.monotonic()
        sampled = began
        for querier in queriers:
            querier.start()
        while time.monotonic() - began < args.seconds:
            if client.get(f"/api/runs/{run_ids[-1]}").json()["status"] != "running":
                run_ids.append(int(client.post("/api/runs", json=RUN).json()["id"]))
            if time.monotonic() - sampled >= args.sample_seconds:
                sampled += args.sample_seconds
                for name, pid in pids.items():
                    series[name].append(rss_mib(pid))
            stop_queries.wait(min(2.0, args.sample_seconds))
        stop_queries.set()
        for querier in queriers:
            querier.join(30)
        for name, pid in pids.items():
            series[name].append(rss_mib(pid))
            shmem[name] = max(shmem[name], rss_mib(pid, "RssShmem"))
        generations = sum(int(client.get(f"/api/runs/{r}").json()["generation"]) for r in run_ids)
        halt.set()
        reports = [out.get(timeout=120) for _ in robot_procs]
        for p in robot_procs:
            p.join(30)
        threading.Event().wait(2.0)  # the last acknowledged batches are committed
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as conn:
            rows = conn.execute(
                "SELECT robot_id, boot, sum(count), max(last), min(first) FROM robot_traces "
                "GROUP BY robot_id, boot"
            ).fetchall()
        client.close()
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
        for proc in procs.values():
            proc.wait(30)
        for p in robot_procs:
            if p.is_alive():
                p.kill()
    stored = sum(int(r[2]) for r in rows)
    gaps = sum(int(r[3]) - int(r[4]) + 1 - int(r[2]) for r in rows)
    lat = np.array(latencies) * 1000
    print(f"\nload report ({args.seconds:.0f} s, load average {os.getloadavg()[0]:.1f})")
    print(f"  robots reporting {len({r[0] for r in rows})}, samples stored {stored}, gaps {gaps}")
    print(
        f"  produced {sum(r['produced'] for r in reports)}, unsent at stop "
        f"{sum(r['unsent'] for r in reports)}, dropped {sum(r['dropped'] for r in reports)}"
    )
    print(
        f"  status queries {len(lat)} ({len(lat) / args.seconds:.1f}/s): p50 "
        f"{np.percentile(lat, 50):.1f} ms, p99 {np.percentile(lat, 99):.1f} ms, max {lat.max():.1f} ms"
    )
    print(f"  generations evolved {generations} over {len(run_ids)} run(s)")
    print(f"  RSS in MiB every {args.sample_seconds:.0f} s (last: at stop)")
    for name, values in series.items():
        shm = f" (of it shared memory, max {shmem[name]:.0f})"
        print(f"  RSS {name:9s} " + " ".join(f"{v:.0f}" for v in values) + shm)
    sys.exit(0 if gaps == 0 else 1)


if __name__ == "__main__":
    main()
