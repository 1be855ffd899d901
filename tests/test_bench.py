"""The bench scripts that take a size still run on a tiny one (`make bench` stops at the first
that fails; figures are not checked here, only that each script gets to print them)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.mark.parametrize(
    ("script", "args", "printed"),
    [
        (
            "stuck.py",
            [
                *("--robots", "4", "--steps", "100", "--window", "20"),
                *("--champions", "1", "--champion-steps", "60"),
            ],
            "false",
        ),
        (
            "field.py",
            [
                "--robots",
                "2",
                "--horizons",
                "150",
                "--hours",
                "0.005",
                "--seeds",
                "1",
                "--minutes",
                "0.2",
                "--candidates",
                "4",
            ],
            "alarms per robot-hour",
        ),
        (
            "explore.py",
            [
                "--quick",
                "--networks",
                "reactive",
                "--generations",
                "2",
                "--poses",
                "20",
                "--steps",
                "300",
            ],
            "validation share",
        ),
        (
            "explore.py",
            ["--speed", "--generations", "2", "--poses", "20", "--steps", "150", "--rounds", "1"],
            "watched kernel / numpy reference",
        ),
        (
            "dispatch.py",
            [
                "--only",
                "throughput",
                "--seconds",
                "0.2",
                "--windows",
                "1",
                "--workers",
                "1",
                "--rounds",
                "20",
            ],
            "per empty job",
        ),
        (
            "study.py",
            ["--quick", "--seeds", "1", "--repeats", "1", "--big-seeds", "1", "--workers", "1"],
            "workers busy at 10x the trial length",
        ),
        (
            "strategies_study.py",
            [
                "--quick",
                "--strategies",
                "paper-ga",
                "novelty",
                "--generations",
                "2",
                "--poses",
                "20",
            ],
            "targets hold:",
        ),
        ("cli.py", ["--repeats", "1"], "colony run list"),
        (
            "evolve.py",
            ["--repeats", "1", "--flags", "--population 8 --generations 2 --steps 10"],
            "of which validation",
        ),
    ],
)
def test_a_bench_script_runs_on_a_tiny_size(script: str, args: list[str], printed: str) -> None:
    done = subprocess.run(
        [sys.executable, str(BENCH / script), *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=BENCH.parent,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert printed in done.stdout
