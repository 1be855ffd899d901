"""What a user sets up: the Makefile's virtual environments."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def make_dry_run(tmp: Path, target: str) -> str:
    """The commands `make TARGET` would run in a fresh clone (no .venv yet)."""
    for name in ("Makefile", "pyproject.toml"):
        shutil.copy(ROOT / name, tmp / name)
    done = subprocess.run(
        ["make", "-n", target], cwd=tmp, capture_output=True, text=True, timeout=30, check=True
    )
    return done.stdout


@pytest.mark.parametrize("target", ["demo", "bench", "chaos", "load"])
def test_running_the_product_installs_the_runtime_dependencies_only(
    tmp_path: Path, target: str
) -> None:
    commands = make_dry_run(tmp_path, target)
    assert "pip install --quiet -e ." in commands
    assert "[dev]" not in commands


@pytest.mark.parametrize("target", ["test", "lint"])
def test_testing_and_linting_install_the_dev_extras(tmp_path: Path, target: str) -> None:
    assert "pip install --quiet -e '.[dev]'" in make_dry_run(tmp_path, target)
