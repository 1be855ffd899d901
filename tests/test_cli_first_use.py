"""What a new user meets on the CLI: `colony evolve` saying when it compiles the simulator;
against a real server, runs named and tagged, exports that rerun, a server URL given with /api,
maze files named as files, piped tables kept whole; `colony server --help` with its defaults
and environment variables."""

from __future__ import annotations

import json
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from colony.cli import app
from schemas.run import RunConfig
from server.core.settings import Settings
from tests.helpers import COLONY, QUICK, Served, completed_run, serve

COMPILING = "compiling the simulator, once per machine: about 15 s"
BAD_CHARACTER = "#####\n#..x#\n#####\n"
NO_ROOM = "#####\n#...#\n#####\n"


def colony(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})
    return result.exit_code, result.output


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    with serve(tmp_path_factory.mktemp("first-use")) as served:
        yield served


# ----------------------------------------------------------------------------- first run


def test_evolve_says_so_while_it_compiles_the_simulator(tmp_path: Path) -> None:
    """A kernel cache of its own: the first run compiles, as on a new machine; the next does
    not, and says nothing."""
    args = [*COLONY, "evolve", "--population", "8", "--generations", "2", "--steps", "10"]
    env = {**os.environ, "EVOCOLONY_KERNEL_CACHE": str(tmp_path / "kernels")}
    outputs = []
    for run in ("first", "second"):
        done = subprocess.run(
            [*args, "--out", str(tmp_path / run)],
            capture_output=True,
            text=True,
            timeout=300,
            env=env,
        )
        assert done.returncode == 0, done.stderr
        outputs.append(done.stdout.splitlines())
    first, second = outputs
    assert first[0].startswith("evolving: ") and first[1] == COMPILING
    assert second[0].startswith("evolving: ") and COMPILING not in second


# ---------------------------------------------------------------------- naming and exports


def test_run_start_names_and_tags_a_run(server: Served) -> None:
    code, out = colony(
        "run", "start", "--population", "8", "--generations", "1", "--steps", "5",
        "--name", "whiskers at 25 mm", "--tag", "gap", "--tag", "seed:3",
        "--server", server.url, "--json",
    )  # fmt: skip
    assert code == 0, out
    run = json.loads(out)
    assert run["name"] == "whiskers at 25 mm" and run["tags"] == ["gap", "seed:3"]
    code, out = colony("run", "list", "--server", server.url)
    assert code == 0 and "whiskers at 25 mm" in out
    code, out = colony("run", "start", "--tag", "no spaces", "--server", server.url)
    assert code == 1 and "error 422" in out and "tags" in out


def test_run_export_writes_config_and_best_that_evolve_reruns(
    server: Served, tmp_path: Path
) -> None:
    run_id = completed_run(server.url, QUICK)
    exported = tmp_path / "exported"
    code, out = colony("run", "export", str(run_id), "--out", str(exported), "--server", server.url)
    assert code == 0, out
    assert {"config.json", "best.json", "generations.csv", "individuals.parquet"} <= {
        p.name for p in exported.iterdir()
    }
    assert str(exported / "best.json") in out.split()
    best = json.loads((exported / "best.json").read_text())
    assert best["validation"] is not None  # the champion of the completed run
    config = RunConfig.model_validate_json((exported / "config.json").read_text())
    assert config == RunConfig.model_validate({**QUICK})

    rerun = tmp_path / "rerun"
    done = subprocess.run(
        [*COLONY, "evolve", "--config", str(exported / "config.json"), "--out", str(rerun)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert json.loads((rerun / "best.json").read_text())["sha256"] == best["sha256"]
    assert (rerun / "config.json").read_text() == (exported / "config.json").read_text()


# ------------------------------------------------------------------------------ small ones


def test_a_server_url_ending_in_api_is_named(server: Served) -> None:
    code, out = colony("run", "list", "--server", f"{server.url}/api")
    assert code == 1
    assert out.strip() == (
        f"error 404: Not Found (the server URL is the base, without /api: --server {server.url})"
    )
    code, out = colony("evaluate", "--server", f"{server.url}/api/", "--run", "1")
    assert code != 0 and f"without /api: --server {server.url})" in out


def test_a_maze_file_is_named_by_its_file(server: Served, tmp_path: Path) -> None:
    bad, tight = tmp_path / "bad.txt", tmp_path / "tight.txt"
    bad.write_text(BAD_CHARACTER)
    tight.write_text(NO_ROOM)
    code, out = colony("run", "start", "--maze", str(bad), "--server", server.url)
    assert code == 1, out
    assert f"error 422: maze: maze file {bad} line 2: unexpected character" in out
    for maze, named in ((bad, "line 2: unexpected character"), (tight, "has no room")):
        code, out = colony("evolve", "--maze", str(maze), "--out", str(tmp_path / "out"))
        assert code == 2, out
        assert f"maze file {maze} {named}" in out and "<text>" not in out


def test_piped_tables_keep_their_width(server: Served) -> None:
    name = "a run with a name far longer than a terminal of eighty columns would show whole"
    code, out = colony("run", "start", "--generations", "1", "--population", "8",
                       "--name", name, "--server", server.url)  # fmt: skip
    assert code == 0, out
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    done = subprocess.run(
        [*COLONY, "run", "list", "--server", server.url],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert done.returncode == 0, done.stderr
    row = next(line for line in done.stdout.splitlines() if name in line)
    assert len(row) > 80 and "paper-ga" in row


def test_server_help_shows_defaults_and_the_env_var_of_each_flag() -> None:
    code, out = colony("server", "--help")
    assert code == 0
    text = " ".join(out.replace("│", " ").split())  # the help panel's cells, unwrapped
    defaults = Settings.model_fields
    for flag, field in (
        ("--db", "db_url"),
        ("--host", "host"),
        ("--port", "port"),
        ("--log-level", "log_level"),
        ("--log-format", "log_format"),
        ("--replacement", "replacement"),
        ("--maze", "maze"),
    ):
        shown = text[text.index(flag) :].split("--", 2)[1]
        assert f"[COLONY_{field.upper()}; default: {defaults[field].default}]" in shown, flag
    assert "default: tcp/127.0.0.1:7447]" in text
    assert "[COLONY_READ_OPEN=false;" in text and "[COLONY_READ_OPEN]" not in text
    assert "[COLONY_ZENOH=false]" in text and "[COLONY_ZENOH]" not in text
