"""How many virtual EvBots one server sustains: trace loss and control-loop jitter.

One server process part (zenoh router + RobotService on a fresh SQLite file) in this process;
the robots (BasicX emulator on a pty + BasicXDriver + Agent, each) run in `--procs` spawned
processes. Every robot runs a random paper-best controller for `--seconds`, then the figures:
samples produced, stored by the server, still buffered, dropped; lateness of each control step
after its deadline (p50, p99, max over every step of every robot); achieved steps/s per robot.

    .venv/bin/python bench/colony.py --robots 16,32,64 --seconds 20
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import queue
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from sqlalchemy import func, select

from evorobotics.document import ControllerDocument
from robot_agent.agent import Agent, AgentSettings
from robot_agent.driver import BasicXDriver
from robot_agent.emulator import BasicXEmulator
from robot_agent.sim_body import SimBody
from schemas.network import NetworkSpec
from server.core.db import make_engine, upgrade
from server.robots.service import RobotService
from server.robots.store import TraceRow


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def robots_process(
    first: int, count: int, endpoint: str, seconds: float, state: str, out: Any, switch: float
) -> None:
    """Run `count` virtual robots for `seconds`, then report their figures on `out`."""
    sys.setswitchinterval(switch)  # many threads share one GIL: hand it over sooner
    spec = NetworkSpec()
    rigs = []
    for i in range(first, first + count):
        rng = np.random.default_rng(i)
        doc = ControllerDocument(spec, rng.uniform(-1, 1, spec.weight_count))
        state_dir = Path(state) / f"r{i}"
        state_dir.mkdir(parents=True)
        (state_dir / "controller.json").write_text(doc.to_json())
        emulator = BasicXEmulator(SimBody.create("paper", seed=0, index=i)).start()
        driver = BasicXDriver.open(emulator.port_path)
        settings = AgentSettings(f"r{i}", connect=(endpoint,), state_dir=state_dir)
        rigs.append((emulator, driver, Agent(settings, driver)))
    for _, _, agent in rigs:
        agent.start()
    for _, _, agent in rigs:  # connected and past the first (compiling) steps
        agent.connected.wait(60)
        agent.wait_for(lambda a=agent: a.steps >= 20, 60)  # type: ignore[misc]
    began = time.monotonic()
    start_steps = [agent.steps for _, _, agent in rigs]
    threading.Event().wait(seconds)
    elapsed = time.monotonic() - began
    steps = [agent.steps - s for (_, _, agent), s in zip(rigs, start_steps, strict=True)]
    # lateness of the steps inside the window only (the deque keeps the last 1000)
    late = np.concatenate(
        [np.array(agent.lateness()[-n:]) for (_, _, agent), n in zip(rigs, steps, strict=True)]
    )
    deadline = time.monotonic() + 10  # let the last batches go out
    for _, _, agent in rigs:
        agent.wait_for(lambda a=agent: a.buffered() < 20, max(0.0, deadline - time.monotonic()))  # type: ignore[misc]
    for emulator, driver, agent in rigs:
        agent.stop()
        driver.close()
        emulator.stop()
    report = {
        "produced": sum(agent.steps for _, _, agent in rigs),
        "unsent": sum(agent.buffered() for _, _, agent in rigs),
        "dropped": sum(agent.dropped for _, _, agent in rigs),
        "serial_errors": sum(agent.serial_errors for _, _, agent in rigs),
        "late": late.tolist(),
        "rate": float(np.mean(steps)) / elapsed,
    }
    out.put(report)


def trial(robots: int, seconds: float, procs: int, switch: float) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as tmp:
        engine = make_engine(f"sqlite:///{tmp}/colony.db")
        upgrade(engine)
        conf = zenoh.Config()
        conf.insert_json5("mode", '"router"')
        conf.insert_json5("listen/endpoints", f'["{endpoint}"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        with zenoh.open(conf) as session:
            service = RobotService(session, engine).start()
            cpu0, wall0 = time.process_time(), time.monotonic()
            ctx = mp.get_context("spawn")
            out = ctx.Queue()
            shares = [robots // procs + (1 if k < robots % procs else 0) for k in range(procs)]
            workers = []
            first = 0
            for k, count in enumerate(shares):
                if count:
                    p = ctx.Process(
                        target=robots_process,
                        args=(first, count, endpoint, seconds, f"{tmp}/p{k}", out, switch),
                    )
                    p.start()
                    workers.append(p)
                first += count
            reports = []
            for _ in workers:
                try:
                    reports.append(out.get(timeout=seconds + 180))
                except queue.Empty:
                    break
            for p in workers:
                p.join(30)
            server_cpu = (time.process_time() - cpu0) / (time.monotonic() - wall0)
            service.close()
        with engine.connect() as db:  # per robot: samples stored and the highest step
            rows = db.execute(
                select(
                    TraceRow.robot_id, func.sum(TraceRow.count), func.max(TraceRow.last)
                ).group_by(TraceRow.robot_id)
            ).all()
        engine.dispose()
    stored = sum(int(r[1]) for r in rows)
    gaps = sum(int(r[2]) + 1 - int(r[1]) for r in rows)  # steps missing below the highest
    produced = sum(r["produced"] for r in reports)
    unsent = sum(r["unsent"] for r in reports)
    dropped = sum(r["dropped"] for r in reports)
    late = np.array([x for r in reports for x in r["late"]]) * 1000
    rate = float(np.mean([r["rate"] for r in reports]))
    print(
        f"{robots:4d} robots in {procs} procs ({len(rows)} reporting)  {rate:5.2f} steps/s each  "
        f"produced {produced:6d}  stored {stored:6d}  unsent at stop {unsent:3d}  "
        f"gaps {gaps}  dropped {dropped}  lateness ms p50 {np.percentile(late, 50):5.2f}  "
        f"p99 {np.percentile(late, 99):6.2f}  max {late.max():7.2f}  "
        f"server CPU {server_cpu:.0%} of a core",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--robots", default="8,16,32,64", help="comma-separated robot counts")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--procs", type=int, default=4, help="processes hosting the robots")
    parser.add_argument(
        "--switch-ms", type=float, default=1.0, help="GIL switch interval of the robot processes"
    )
    args = parser.parse_args()
    for n in (int(x) for x in args.robots.split(",")):
        trial(n, args.seconds, args.procs, args.switch_ms / 1000)


if __name__ == "__main__":
    main()
