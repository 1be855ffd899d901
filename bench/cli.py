"""Start-up time of the `colony` CLI: `--help`, and the two REST clients `run list` and `status`
against a real server (`colony server --no-zenoh`, a fresh SQLite file, on loopback).

Each command runs as its own process, `--repeats` times; prints the median wall time and the
median CPU time (user + system, less disturbed by other load on the machine). With `--against
DIR` (a checkout of another commit), the same commands also run from DIR's code, interleaved
(this tree, DIR, this tree, ...) so a drift of the machine's load falls on both alike, and the
ratios are printed.

    .venv/bin/python bench/cli.py --repeats 15 --against /tmp/before
"""

from __future__ import annotations

import argparse
import os
import resource
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

START_S = 60.0
ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def timed(argv: list[str], env: dict[str, str], cwd: str) -> tuple[float, float]:
    """Wall and CPU seconds of one run of `argv` in `cwd` (off any checkout, which `python -c`
    would put before PYTHONPATH), which must succeed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    subprocess.run(argv, env=env, cwd=cwd, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    return wall, cpu


def wait_healthy(url: str, server: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + START_S
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise SystemExit(f"the server exited with {server.returncode}")
        try:
            if httpx.get(f"{url}/healthz", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise SystemExit(f"no server at {url} after {START_S} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--against", type=Path, help="a checkout of another commit to compare")
    args = parser.parse_args()
    colony = [sys.executable, "-c", "from colony.cli import main; main()"]
    trees = {"this tree": ROOT, **({str(args.against): args.against} if args.against else {})}
    envs = {
        name: {**os.environ, "PYTHONPATH": str(tree), "COLUMNS": "120"}
        for name, tree in trees.items()
    }
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        server = subprocess.Popen(
            [*colony, "server", "--no-zenoh", "--db", f"sqlite:///{tmp}/c.db", "--port", str(port)],
            cwd=tmp,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            wait_healthy(url, server)
            commands = {
                "colony --help": ["--help"],
                "colony run list": ["run", "list", "--server", url],
                "colony status": ["status", "--server", url],
            }
            times: dict[tuple[str, str], list[tuple[float, float]]] = {
                (c, t): [] for c in commands for t in trees
            }
            for _ in range(args.repeats):
                for command, argv in commands.items():
                    for tree in trees:
                        times[command, tree].append(timed([*colony, *argv], envs[tree], tmp))
        finally:
            server.terminate()
            server.wait(timeout=30)
    print(f"median of {args.repeats} runs, seconds (wall / cpu)")
    for command in commands:
        medians = {
            tree: (
                statistics.median(w for w, _ in times[command, tree]),
                statistics.median(c for _, c in times[command, tree]),
            )
            for tree in trees
        }
        cells = [f"{tree}: {w:.3f} / {c:.3f}" for tree, (w, c) in medians.items()]
        if args.against:
            (w0, c0), (w1, c1) = medians.values()
            cells.append(f"ratio {w1 / w0:.1f}x / {c1 / c0:.1f}x")
        print(f"{command:16s} " + "   ".join(cells))


if __name__ == "__main__":
    main()
