"""What a user sets up: the Makefile's virtual environments, the example systemd units."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
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


@pytest.mark.parametrize("target", ["demo", "bench", "load"])
def test_running_the_product_installs_the_runtime_dependencies_only(
    tmp_path: Path, target: str
) -> None:
    commands = make_dry_run(tmp_path, target)
    assert "pip install --quiet -e ." in commands
    assert "[dev]" not in commands


@pytest.mark.parametrize("target", ["test", "lint", "chaos"])
def test_testing_and_linting_install_the_dev_extras(tmp_path: Path, target: str) -> None:
    assert "pip install --quiet -e '.[dev]'" in make_dry_run(tmp_path, target)


def systemd_units() -> dict[str, str]:
    """docs/deployment.md's example units by file name."""
    text = (ROOT / "docs" / "deployment.md").read_text()
    names = re.findall(r"`/etc/systemd/system/([\w@.-]+\.service)`", text)
    bodies = re.findall(r"```ini\n(.*?)```", text, re.DOTALL)
    assert len(names) == len(bodies) == 3
    return dict(zip(names, bodies, strict=True))


@pytest.mark.parametrize(
    "name", ["evocolony-server.service", "evocolony-worker@.service", "evocolony-agent.service"]
)
def test_an_example_unit_runs_a_command_with_flags_that_exist(name: str) -> None:
    import typer.main

    from colony.cli import app

    unit = systemd_units()[name]
    argv = shlex.split(re.findall(r"^ExecStart=(.*)$", unit, re.MULTILINE)[0])
    assert argv[0] == "/opt/evocolony/bin/colony"
    command = typer.main.get_group(app).commands[argv[1]]
    flags = {opt for param in command.params for opt in param.opts}
    assert {a for a in argv[2:] if a.startswith("--")} <= flags, argv


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="needs systemd-analyze")
def test_the_example_units_pass_systemd_analyze_verify(tmp_path: Path) -> None:
    colony = Path(sys.executable).parent / "colony"
    for name, body in systemd_units().items():
        unit = tmp_path / name.replace("@.", "@1.")  # a template is verified as an instance
        unit.write_text(body.replace("/opt/evocolony/bin/colony", str(colony)))
        done = subprocess.run(
            ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60
        )
        assert done.returncode == 0 and done.stderr == "", (name, done.stderr)
