"""What a lab user types: mazes and networks checked before a run starts (CLI and REST alike),
sha256 prefixes, one robot view in the API and the tables, one-line errors, follow."""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
import numpy as np
import pytest
from sqlalchemy.orm import Session
from typer.testing import CliRunner

from colony.cli import app
from colony.robot_cli import ago
from evorobotics.evolution import evolve
from schemas.network import PRESETS
from schemas.run import RunConfig
from server.core.db import make_engine, upgrade
from server.core.errors import InvalidInputError, NotFoundError
from server.core.settings import Settings
from server.runs import crud
from tests.helpers import (
    QUICK,
    SMALL,
    Colony,
    completed_run,
    eventually,
    free_port,
    online,
    robot_link,
    serving,
    virtual_robot,
    wait_status,
    worker_thread,
)
from worker.main import WorkerSettings, WorkerStats, evaluate_slice, run_worker

NO_ROOM = "#####\n#...#\n#####\n"
"""A maze with free cells but none the robot's body fits in."""


def colony(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})
    return result.exit_code, result.output


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Colony]:
    """A server with one in-process evaluator and a completed QUICK run (its champion stored)."""
    tmp = tmp_path_factory.mktemp("inputs")
    db_url = f"sqlite:///{tmp / 'colony.db'}"
    settings = Settings(db_url=db_url, port=free_port(), executors=1, zenoh=False)
    with serving(settings) as (url, served):
        yield Colony(url, db_url, completed_run(url, QUICK), served, tmp)


# ------------------------------------------------------------------------ mazes and networks


@pytest.mark.parametrize(
    ("maze", "named"),
    [
        ("gen:999:1", "1..64"),
        ("gen:0:1", "1..64"),
        ("gen:x", "gen:SIZE:SEED"),
        ("no such maze", "not a shipped maze"),
        ("/etc/hostname", "not a shipped maze"),
        ("ab\ncd\n", "unexpected character"),
        (NO_ROOM, "no room for the robot"),
    ],
)
def test_a_run_with_a_bad_maze_is_refused_at_creation(
    server: Colony, maze: str, named: str
) -> None:
    with httpx.Client(base_url=server.url, timeout=30) as client:
        before = len(client.get("/api/runs").json())
        refused = client.post("/api/runs", json={**SMALL, "maze": maze})
        assert refused.status_code == 422, refused.text
        detail = refused.json()["detail"]
        assert detail.startswith("maze: ") and named in detail
        assert len(client.get("/api/runs").json()) == before  # nothing was started


def test_evolve_refuses_the_same_mazes_in_one_line(tmp_path: Path) -> None:
    binary = tmp_path / "maze.bin"
    binary.write_bytes(bytes(range(256)))
    no_room = tmp_path / "tight.txt"
    no_room.write_text(NO_ROOM)
    for maze, named in (
        (str(binary), f"maze file {binary}: not a text maze file"),
        (str(no_room), "no room for the robot"),
        ("gen:999:1", "1..64"),
    ):
        code, out = colony("evolve", "--maze", maze, "--out", str(tmp_path / "out"))
        assert code == 2, out
        assert named in out and "Traceback" not in out and len(out.strip().splitlines()) == 1


def test_run_start_sends_maze_and_network_files_and_the_nominal_world(
    server: Colony, tmp_path: Path
) -> None:
    maze = tmp_path / "room.txt"
    maze.write_text(
        "; a room\n" + "#" * 12 + "\n" + ("#" + "." * 10 + "#\n") * 10 + "#" * 12 + "\n"
    )
    network = tmp_path / "net.json"
    network.write_text(PRESETS["reactive"].model_dump_json())
    code, out = colony(
        "run", "start", "--population", "8", "--generations", "1", "--steps", "5",
        "--maze", str(maze), "--network", str(network), "--nominal",
        "--server", server.url, "--json",
    )  # fmt: skip
    assert code == 0, out
    config = RunConfig.model_validate(json.loads(out)["config"])
    assert config.maze == maze.read_text() and config.reality_gap == "off"
    assert config.network_spec == PRESETS["reactive"]
    binary = tmp_path / "maze.bin"
    binary.write_bytes(b"\xff\xfe\x00")
    code, out = colony("run", "start", "--maze", str(binary), "--server", server.url)
    assert code == 2 and "not a text maze file" in out
    code, out = colony("run", "start", "--maze", "gen:0:1", "--server", server.url)
    assert code == 1 and "error 422: maze: " in out and "Traceback" not in out


# ----------------------------------------------------------------------------- sha prefixes


def test_controllers_are_found_by_an_unambiguous_prefix(server: Colony) -> None:
    with httpx.Client(base_url=server.url, timeout=30) as client:
        sha = client.get(f"/api/runs/{server.run_id}/best").json()["sha256"]
        for prefix in (sha[:8], sha[:12].upper(), sha):
            found = client.get(f"/api/controllers/{prefix}")
            assert found.status_code == 200 and found.json()["sha256"] == sha, prefix
        report = client.get(f"/api/controllers/{sha[:12]}/evaluation?poses=2&steps=5")
        assert report.status_code == 200 and report.json()["sha256"] == sha
        short = client.get(f"/api/controllers/{sha[:7]}")
        assert short.status_code == 422 and "8 to 64 hex digits" in short.json()["detail"]
        unknown = "0" * 8 if not sha.startswith("0" * 8) else "f" * 8
        missing = client.get(f"/api/controllers/{unknown}")
        assert missing.status_code == 404 and unknown in missing.json()["detail"]


def test_an_ambiguous_prefix_names_the_problem(tmp_path: Path) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'c.db'}")
    upgrade(engine)
    with Session(engine) as db:
        for sha in ("abcdef01" + "0" * 56, "abcdef01" + "1" * 56):
            crud.put_controller(
                db, sha256=sha, document="{}", run_id=None, generation=None, fitness=None
            )
        db.commit()
        with pytest.raises(InvalidInputError, match="ambiguous"):
            crud.find_controller(db, sha256="abcdef01")
        assert crud.find_controller(db, sha256="abcdef011").sha256.endswith("1" * 56)
        with pytest.raises(NotFoundError):
            crud.find_controller(db, sha256="abcdef02")
    engine.dispose()


# --------------------------------------------------------------------------- one robot view


def test_robots_and_status_show_one_robot_view(server: Colony, tmp_path: Path) -> None:
    with (
        robot_link(server) as link,
        virtual_robot("r-view", link, tmp_path),
        httpx.Client(base_url=server.url, timeout=30) as client,
    ):
        assert eventually(lambda: online(client, "r-view"))
        sha = client.get(f"/api/runs/{server.run_id}/best").json()["sha256"]
        push = client.post("/api/robots/r-view/controller", json={"sha256": sha[:12]})
        assert push.status_code == 200 and push.json()["accepted"], push.text
        assert eventually(lambda: client.get("/api/robots").json()[0]["last_seen"] is not None)
        [robot] = client.get("/api/robots").json()
        assert client.get("/api/colony").json()["robots"] == [robot]
        assert set(robot) == {
            "id", "online", "state", "controller_sha256", "steps", "stuck_events", "last_seen",
            "replacement", "replacement_source",
        }  # fmt: skip
        seen = datetime.fromisoformat(robot["last_seen"])
        assert seen.utcoffset() == timedelta(0)
        assert abs((datetime.now(UTC) - seen).total_seconds()) < 60
        assert robot["online"] and robot["controller_sha256"] == sha
        outputs = [colony(command, "--server", server.url) for command in ("robots", "status")]
    for code, out in outputs:
        assert code == 0, out
        [row] = [line for line in out.splitlines() if "r-view" in line]
        cells = [c.strip() for c in row.strip("│ ").split("│")]
        assert cells[:2] == ["r-view", "yes"], row
        assert sha[:12] in row and " s ago" in row


def test_ago_reads_like_a_person() -> None:
    now = datetime(2026, 1, 1, 12, 0, tzinfo=UTC)
    assert ago(None, now) == "never"
    assert ago((now - timedelta(seconds=12)).isoformat(), now) == "12 s ago"
    assert ago((now - timedelta(minutes=5)).isoformat(), now) == "5 min ago"
    assert ago((now - timedelta(hours=3)).isoformat(), now) == "3 h ago"
    assert ago((now - timedelta(days=4)).isoformat(), now) == "4 d ago"


# ---------------------------------------------------------------------------------- follow


def broken(config: RunConfig, generation: int, genomes: np.ndarray) -> tuple[np.ndarray, ...]:
    raise RuntimeError("simulated evaluator crash")


def test_follow_prints_why_a_run_failed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker's error fails nothing; the server's own evaluation failing fails the run (its
    physics broken here by hand: nothing else makes it fail)."""
    monkeypatch.setattr("server.runs.evaluation.evaluate", broken)
    zport = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        workers=0,
    )
    with serving(settings) as (url, _), httpx.Client(base_url=url, timeout=30) as client:
        stop = threading.Event()
        worker = WorkerSettings(connect=(f"tcp/127.0.0.1:{zport}",), name="crashy")
        thread = threading.Thread(
            target=run_worker, args=(worker, stop), kwargs={"evaluator": broken}
        )
        thread.start()
        try:
            started = colony("run", "start", *_flags(SMALL), "--follow", "--server", url)
            sets = [f"--set={k}={v}" for k, v in SMALL.items()]
            study = colony("study", "start", "--name", "s", "--seeds", "1", *sets, "--follow",
                           "--server", url)  # fmt: skip
        finally:
            stop.set()
            thread.join(timeout=30)
        run_id, study_run = (r["id"] for r in client.get("/api/runs").json()[::-1])
        wait_status(client, run_id, {"failed"})
        again = colony("run", "follow", str(run_id), "--server", url)
        shown = colony("run", "show", str(run_id), "--server", url)
        monkeypatch.undo()  # the physics mended: resumed, the run goes on where it stopped
        with worker_thread(zport, "honest", evaluate_slice):
            resumed = colony("run", "resume", str(run_id), "--server", url)
            done = wait_status(client, run_id, {"completed", "failed"})
    assert resumed[0] == 0, resumed[1]
    assert (done["status"], done["error"]) == ("completed", None)
    assert done["best_fitness"] == evolve(RunConfig(**SMALL)).history[-1].best
    why = "job 0/0 failed in the server's own evaluation: RuntimeError: simulated"
    for code, out in (started, again):
        assert code == 1, out
        assert f"run {run_id} failed: {why}" in out
    assert shown[0] == 0 and f"failed: {why}" in shown[1]
    assert study[0] == 1 and f"run {study_run} (s/base/0) failed: {why}" in study[1]


class _Interrupted(httpx.HTTPTransport):
    """The real server, until the polls of a follow meet a Ctrl-C (KeyboardInterrupt)."""

    def __init__(self, polls: int) -> None:
        super().__init__()
        self.polls = polls

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.method == "GET":
            self.polls -= 1
            if self.polls < 0:
                raise KeyboardInterrupt
        return super().handle_request(request)


def test_ctrl_c_on_follow_names_the_command_that_reattaches(server: Colony) -> None:
    args = ["run", "start", *_flags({**SMALL, "generations": 10_000}), "--follow"]
    result = CliRunner().invoke(
        app, [*args, "--server", server.url], obj={"transport": _Interrupted(polls=2)}
    )
    assert result.exit_code == 130, result.output
    with httpx.Client(base_url=server.url, timeout=30) as client:
        run = client.get("/api/runs").json()[0]
        assert run["status"] == "running"  # following stopped, the run did not
        client.post(f"/api/runs/{run['id']}/cancel")
    assert f"Re-attach: colony run follow {run['id']} --server {server.url}" in result.output
    assert "Traceback" not in result.output


def _flags(config: dict[str, int]) -> list[str]:
    return [item for k, v in config.items() for item in (f"--{k.replace('_', '-')}", str(v))]


# ------------------------------------------------------------------- colony server, mazes


def test_a_taken_port_is_one_line(tmp_path: Path) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        db = f"sqlite:///{tmp_path / 'c.db'}"
        for flags, named in (
            (["--port", str(taken)], f"HTTP on 127.0.0.1:{taken}"),
            (["--port", str(free_port()), "--zenoh-listen", f"tcp/127.0.0.1:{taken}"], "zenoh"),
        ):
            code, out = colony("server", "--db", db, "--workers", "0", *flags)
            assert code == 1 and named in out and "in use" in out, out
            assert len(out.strip().splitlines()) == 1


def test_an_unwritable_database_directory_is_named(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    db = f"sqlite:///{blocker / 'colony.db'}"
    code, out = colony("server", "--db", db, "--port", str(free_port()), "--no-zenoh")
    assert code == 1 and f"database's directory {blocker}" in out, out
    assert len(out.strip().splitlines()) == 1


def test_mazes_lists_the_shipped_ones_and_renders_one(tmp_path: Path) -> None:
    code, out = colony("mazes")
    assert code == 0, out
    for name in ("arena", "corridor", "paper", "zigzag"):
        assert name in out
    assert "24 x 24" in out and "431 (75%)" in out  # paper: cells and free cells
    png = tmp_path / "gen.png"
    code, out = colony("mazes", "gen:3:1", "--png", str(png))
    assert code == 0 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, out = colony("mazes", "gen:99:1")
    assert code == 2 and "1..64" in out


def test_workers_count_the_evaluations_of_the_runs(tmp_path: Path) -> None:
    """Every evaluation the run counts is one a worker sent and the server took; the worker's
    own count adds the late ones the server dropped."""
    zport = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        workers=0,
    )
    with serving(settings) as (url, _), httpx.Client(base_url=url, timeout=30) as client:
        stop = threading.Event()
        stats: list[WorkerStats] = []
        worker = WorkerSettings(connect=(f"tcp/127.0.0.1:{zport}",), name="counted")
        thread = threading.Thread(target=lambda: stats.append(run_worker(worker, stop)))
        thread.start()
        try:
            run_id = client.post("/api/runs", json=SMALL).json()["id"]
            run = wait_status(client, run_id, {"completed"})
            [listed] = client.get("/api/workers").json()
            code, out = colony("workers", "--server", url)
        finally:
            stop.set()
            thread.join(timeout=30)
    assert run["evaluations"] == SMALL["population"] * SMALL["generations"]
    assert listed["evaluations"] == run["evaluations"]
    assert stats[0].evaluations == listed["evaluations"] + listed["late"]
    assert code == 0 and "evaluations" in out
    [row] = [line for line in out.splitlines() if "counted" in line]
    assert f" {run['evaluations']} " in row
