"""Wall time of `colony evolve` (the paper's experiment by default) as a process, and its parts.

Each run is a fresh `colony evolve --out TMP` process, `--repeats` times, with the numba kernels
cached (a first run warms them and is not counted). Prints the median wall time of the process
and of its parts: start-up and imports (the process's wall minus what the command timed
itself), evolution, the champion's validation (part of evolution) and writing the files and
plots. With `--against DIR` (a checkout of another commit) the same command also runs from
DIR's code, interleaved (this tree, DIR, this tree, ...) so a drift of the machine's load falls
on both alike, and the ratio is printed.

    .venv/bin/python bench/evolve.py --repeats 5 --against /tmp/before
    .venv/bin/python bench/evolve.py --flags "--threads 1"
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("start-up and imports", "evolution", "of which validation", "files and plots")
WALL_LINE = re.compile(
    r"wall time (?P<total>[\d.]+) s \(evolution (?P<evolution>[\d.]+) s"
    r"(?:, of which validation (?P<validation>[\d.]+) s)?[;,] files (?P<files>[\d.]+) s\)"
)


def run(flags: list[str], env: dict[str, str], cwd: str) -> dict[str, float]:
    """One `colony evolve` process: its wall time and its parts (NaN for a part it does not
    report), from its own last line."""
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", "from colony.cli import main; main()", "evolve", *flags],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"colony evolve {' '.join(flags)} failed:\n{done.stderr[-2000:]}")
    found = WALL_LINE.search(done.stdout)
    if found is None:
        raise SystemExit(f"no wall time line in the output of colony evolve:\n{done.stdout}")
    total = float(found["total"])
    return {
        "wall": wall,
        "start-up and imports": wall - total,
        "evolution": float(found["evolution"]),
        "of which validation": float(found["validation"] or "nan"),
        "files and plots": float(found["files"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--against", type=Path, help="a checkout of another commit to compare")
    parser.add_argument("--flags", default="", help="more colony evolve flags, one string")
    args = parser.parse_args()
    trees = {"this tree": ROOT, **({str(args.against): args.against} if args.against else {})}
    envs = {name: {**os.environ, "PYTHONPATH": str(tree)} for name, tree in trees.items()}
    times: dict[str, list[dict[str, float]]] = {tree: [] for tree in trees}
    with tempfile.TemporaryDirectory() as tmp:  # off any checkout, as `python -c` puts cwd first
        flags = ["--out", f"{tmp}/out", *shlex.split(args.flags)]
        for tree in trees:
            run(flags, envs[tree], tmp)  # compile or load the kernels once
        for _ in range(args.repeats):
            for tree in trees:
                times[tree].append(run(flags, envs[tree], tmp))
    print(f"colony evolve {args.flags}".rstrip() + f": median of {args.repeats} runs, seconds")
    medians = {
        tree: {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        for tree, runs in times.items()
    }
    for tree, m in medians.items():
        parts = ", ".join(f"{p} {m[p]:.2f}" for p in PARTS)
        print(f"{tree}: wall {m['wall']:.2f} ({parts})")
    if args.against:
        mine, other = (m["wall"] for m in medians.values())
        print(f"wall ratio, this tree / {args.against}: {mine / other:.2f}x")


if __name__ == "__main__":
    main()
