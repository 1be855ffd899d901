"""The `colony` entry point stays light: the simulator, plotting, zenoh, the server's stack and
the data libraries are imported only by the commands that use them (timings: bench/cli.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import serve

pytestmark = pytest.mark.slow  # each test starts a Python process

HEAVY = (
    "numba",
    "llvmlite",
    "numpy",
    "scipy",
    "matplotlib",
    "pyarrow",
    "zenoh",
    "fastapi",
    "starlette",
    "uvicorn",
    "sqlalchemy",
    "alembic",
    "cma",
    "ribs",
    "tensorboardX",
    "yaml",
    "evorobotics.sim",
    "evorobotics.network",
    "server",
    "worker",
    "robot_agent",
    "httpx._main",
)
"""Packages (and modules) no start-up of the CLI or of its REST clients needs."""

REPORT = """
import sys
from colony.cli import main
if sys.argv[1:]:
    sys.argv = ["colony", *sys.argv[1:]]
    try:
        main()
    except SystemExit as exc:
        assert not exc.code, exc.code
print("\\n".join(m for m, module in sys.modules.items() if module is not None), file=sys.stderr)
"""
"""Imports the CLI, runs `colony ARGS` if given, and prints every module loaded on stderr."""


def heavy_imports(cwd: Path, *args: str) -> set[str]:
    """The HEAVY packages or modules that `colony ARGS` (or `import colony.cli` with none)
    imported, in a fresh interpreter."""
    done = subprocess.run(
        [sys.executable, "-c", REPORT, *args], cwd=cwd, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    loaded = set(done.stderr.split())
    return {h for h in HEAVY if h in loaded or any(m.startswith(h + ".") for m in loaded)}


def test_importing_the_cli_imports_no_heavy_package(tmp_path: Path) -> None:
    assert heavy_imports(tmp_path) == set()


def test_help_imports_no_heavy_package(tmp_path: Path) -> None:
    assert heavy_imports(tmp_path, "--help") == set()


def test_the_rest_clients_import_no_heavy_package(tmp_path: Path) -> None:
    with serve(tmp_path) as served:
        for command in (["run", "list"], ["status"]):
            assert heavy_imports(tmp_path, *command, "--server", served.url) == set(), command
