"""Structured logs: JSON lines carrying run, worker and robot ids (docs/configuration.md)."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from schemas.run import RunConfig
from server.core.db import make_engine, upgrade
from server.core.logs import as_format, configure, context
from server.core.settings import Settings
from server.runs.evaluation import run_job
from server.runs.lifecycle import RunManager
from server.runs.writer import LOG_EVERY_S
from tests.helpers import free_port

WAIT = 60.0
COLONY = str(Path(sys.executable).with_name("colony"))


@pytest.fixture
def restore_logging() -> Iterator[None]:
    """`configure` replaces the root handlers: give pytest its own back afterwards."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def test_a_run_through_the_manager_logs_json_lines_with_its_run_id(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], restore_logging: None
) -> None:
    configure("INFO", "json")
    engine = make_engine(f"sqlite:///{tmp_path / 'c.db'}")
    upgrade(engine)
    try:
        manager = RunManager(engine, Settings(db_url="unused"))
        config = RunConfig(population=8, generations=2, steps=10, trials=1, job_size=4)
        run_id = manager.create_run(config)
        while (job := manager.scheduler.lease("w")) is not None:
            assert manager.scheduler.settle(run_job(job, "w")).accepted
            manager.flush()
    finally:
        engine.dispose()
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    entries = [json.loads(line) for line in lines]  # every line is one JSON object
    mine = [e for e in entries if e.get("run") == run_id]
    messages = " | ".join(e["message"] for e in mine)
    for word in ("created", "running", "generation 0 written", "generation 1 written", "completed"):
        assert word in messages, (word, messages)
    assert all(e["level"] == "INFO" for e in mine)
    writer = {e["logger"] for e in mine if "written" in e["message"]}
    others = {e["logger"] for e in mine if "written" not in e["message"]}
    assert (writer, others) == ({"server.runs.writer"}, {"server.runs.lifecycle"})


def test_generation_lines_go_out_at_info_at_most_once_a_second_per_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], restore_logging: None
) -> None:
    """A span writes hundreds of generations a second: the first, the last and one a second
    are INFO, the others DEBUG, and every generation has its line."""
    configure("DEBUG", "json")
    engine = make_engine(f"sqlite:///{tmp_path / 'c.db'}")
    upgrade(engine)
    generations = 40
    try:
        manager = RunManager(engine, Settings(db_url="unused"))
        config = RunConfig(population=8, generations=generations, steps=5, trials=1, job_size=8)
        began = time.monotonic()
        run_id = manager.create_run(config)
        while (job := manager.scheduler.lease("w")) is not None:
            assert manager.scheduler.settle(run_job(job, "w")).accepted
            manager.flush()  # one generation a write, each with its line
        elapsed = time.monotonic() - began
    finally:
        engine.dispose()
    entries = [json.loads(line) for line in capsys.readouterr().err.splitlines() if line.strip()]
    written = [e for e in entries if e.get("run") == run_id and "written" in e["message"]]
    assert [e["message"].split()[3] for e in written] == [str(g) for g in range(generations)]
    loud = [int(e["message"].split()[3]) for e in written if e["level"] == "INFO"]
    assert loud[0] == 0 and loud[-1] == generations - 1
    assert len(loud) <= 3 + elapsed / LOG_EVERY_S, (loud, elapsed)
    assert {e["level"] for e in written} == {"INFO", "DEBUG"}


def test_process_ids_go_on_every_line_and_a_record_s_own_id_wins(
    capsys: pytest.CaptureFixture[str], restore_logging: None
) -> None:
    configure("DEBUG", "text", ids={"worker": "w7"})
    log = logging.getLogger("tests.logs")
    log.debug("plain")
    context(log, worker="other", run=2).info("own")
    err = capsys.readouterr().err.splitlines()
    assert err[0].endswith("DEBUG tests.logs plain [worker=w7]")
    assert err[1].endswith("INFO tests.logs own [run=2 worker=other]")


def test_bad_formats_levels_and_ids_are_refused() -> None:
    with pytest.raises(ValueError, match="text or json"):
        as_format("xml")
    with pytest.raises(ValueError, match="log level"):
        configure("LOUD")
    with pytest.raises(ValueError, match="context ids"):
        configure(ids={"host": "x"})


def first_json_line(path: Path, want: str) -> dict[str, Any] | None:
    """The first JSON line in the log file at `path` whose message contains `want`, waiting up
    to WAIT for it; None if none came."""
    tick, deadline = threading.Event(), time.monotonic() + WAIT
    while time.monotonic() < deadline:
        text = path.read_text()
        for line in text[: text.rfind("\n") + 1].splitlines():  # whole lines only
            entry: dict[str, Any] = json.loads(line)
            if want in entry["message"]:
                return entry
        tick.wait(0.1)
    return None


@pytest.mark.parametrize(
    ("args", "field", "want"),
    [
        (["worker", "--name", "w-logs"], "worker", "no router"),
        (
            ["agent", "--robot-id", "r-logs", "--emulate", "--insecure-no-verify"],
            "robot",
            "r-logs",
        ),
    ],
)
def test_worker_and_agent_lines_carry_their_id(
    tmp_path: Path, args: list[str], field: str, want: str
) -> None:
    """Real processes with no router to reach: their JSON lines name the worker or robot."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    command = [COLONY, *args, "--connect", endpoint, "--log-format", "json"]
    if args[0] == "agent":
        command += ["--state-dir", str(tmp_path), "--log-level", "DEBUG"]
    log_file = tmp_path / "stderr.log"
    with log_file.open("wb") as stderr:
        proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=stderr)
    try:
        entry = first_json_line(log_file, want)
        assert entry is not None, log_file.read_text()
        assert entry[field] == args[2]
    finally:
        proc.kill()
        proc.wait(timeout=WAIT)
