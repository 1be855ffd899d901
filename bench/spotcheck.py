"""What spot-checks cost at the paper's scale: robot-steps re-evaluated, and run wall time.

`colony server --workers W` (its own local worker processes, zenoh on loopback, a fresh SQLite
file) runs the default RunConfig (the paper's experiment) to completion, with
COLONY_SPOT_CHECKS=1 and =0 interleaved (the order alternates every repetition), so a drift
of the machine's load falls on both alike. Per run: wall time from POST /api/runs to
"completed", and the robot-steps evaluated again (/metrics: by the server, or by the workers of
a generation cut into several jobs) against the run's own
evaluation robot-steps (population x generations x trials x trial steps). Both settings must
export the same champion (checks never touch the science).

    .venv/bin/python bench/spotcheck.py --workers 1,2 --repeats 3
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from evorobotics.evaluate import robot_steps
from schemas.run import RunConfig

COLONY = [sys.executable, "-c", "from colony.cli import main; main()"]
TIMEOUT_S = 900.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def metric(text: str, name: str) -> float:
    """A sample's value in the Prometheus text `text` (0 if absent)."""
    found = re.search(rf"^{name} (\S+)$", text, re.MULTILINE)
    return float(found.group(1)) if found else 0.0


def one_run(
    workers: int, checks: int, config: dict[str, Any], tmp: Path, env: dict[str, str]
) -> dict[str, Any]:
    """A fresh server with `workers` local workers (and `env`) runs `config`: its figures."""
    http, zenoh_port = free_port(), free_port()
    db = tmp / f"w{workers}-c{checks}-{time.monotonic_ns()}.db"
    argv = [*COLONY, "server", "--db", f"sqlite:///{db}", "--port", str(http)]
    argv += ["--zenoh-listen", f"tcp/127.0.0.1:{zenoh_port}", "--workers", str(workers)]
    env = {
        **os.environ,
        **env,
        "COLONY_SPOT_CHECKS": str(checks),
        "COLONY_HOUSEKEEPING_SECONDS": "0.2",
    }
    with (tmp / "server.log").open("ab") as log:
        proc = subprocess.Popen(argv, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{http}", timeout=30) as client:
            wait(lambda: _get(client, "/api/workers") is not None, proc)
            wait(lambda: len(_get(client, "/api/workers") or []) == workers, proc)
            began = time.perf_counter()
            run_id = client.post("/api/runs", json=config).json()["id"]
            wait(lambda: client.get(f"/api/runs/{run_id}").json()["status"] != "running", proc)
            seconds = time.perf_counter() - began
            run = client.get(f"/api/runs/{run_id}").json()
            assert run["status"] == "completed", run
            text = client.get("/metrics").text
            best = client.get(f"/api/runs/{run_id}/best").json()["sha256"]
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    full = RunConfig(**config)
    return {
        "seconds": seconds,
        "checked": metric(text, "colony_spot_check_robot_steps_checked_total"),
        "individuals": metric(text, "colony_spot_check_individuals_checked_total"),
        "evaluated": robot_steps(full, full.population) * full.generations,
        "best": best,
    }


def _get(client: httpx.Client, path: str) -> Any:
    try:
        return client.get(path, timeout=1).json()
    except httpx.TransportError:
        return None


def wait(predicate: Any, proc: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not predicate():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError("colony server exited or timed out (see server.log)")
        time.sleep(0.05)  # a poll of a REST view no event announces


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--workers", default="1,2", help="comma-separated local worker counts")
    parser.add_argument("--repeats", type=int, default=3, help="on/off pairs per worker count")
    parser.add_argument("--generations", type=int, default=None, help="default: the paper's")
    parser.add_argument(
        "--span-below",
        type=float,
        default=None,
        help="COLONY_SPAN_BELOW_SECONDS (default the server's: 0.02); e.g. 1 to force spans",
    )
    args = parser.parse_args()
    env = {} if args.span_below is None else {"COLONY_SPAN_BELOW_SECONDS": str(args.span_below)}
    with tempfile.TemporaryDirectory() as name:
        tmp = Path(name)
        for workers in (int(w) for w in args.workers.split(",")):
            runs: dict[int, list[dict[str, Any]]] = {1: [], 0: []}
            for r in range(args.repeats):
                config: dict[str, Any] = {"seed": r}
                if args.generations is not None:
                    config["generations"] = args.generations
                for checks in (1, 0) if r % 2 == 0 else (0, 1):
                    got = one_run(workers, checks, config, tmp, env)
                    runs[checks].append(got)
                    print(
                        f"workers {workers} seed {r} spot_checks {checks}: {got['seconds']:.2f} s, "
                        f"{got['individuals']:.0f} individuals re-evaluated, "
                        f"champion {got['best'][:12]}",
                        flush=True,
                    )
                on, off = runs[1][-1], runs[0][-1]
                assert on["best"] == off["best"], "spot-checks changed the champion"
            cost = sum(g["checked"] for g in runs[1]) / sum(g["evaluated"] for g in runs[1])
            ratios = [a["seconds"] / b["seconds"] for a, b in zip(runs[1], runs[0], strict=True)]
            print(
                f"workers {workers}: spot-check cost: {100 * cost:.2f} % of evaluation "
                f"robot-steps, run wall time on/off ratio {statistics.median(ratios):.3f} "
                f"(median of {len(ratios)} pairs; each {', '.join(f'{x:.3f}' for x in ratios)}; "
                f"mean on {statistics.mean(g['seconds'] for g in runs[1]):.2f} s, "
                f"off {statistics.mean(g['seconds'] for g in runs[0]):.2f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
