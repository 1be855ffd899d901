"""`colony agent` as a lab user runs it: a bad flag is one line naming it, before anything is
fetched or pinned; a missing router is logged once, then less and less often, with its
address; a second agent of the same robot id is refused with the first one's HOST:PID."""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import pytest
import zenoh
from typer.testing import CliRunner

from colony.cli import app
from robot_agent.verify import PINNED_KEY
from schemas.robots import alive_key
from tests.helpers import (
    AGENT_WAIT,
    COLONY,
    WAIT,
    Served,
    client_config,
    free_port,
    router_config,
    serve,
)

GARBAGE = "garbage\n"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """A server whose key an agent would fetch and pin (trust on first use)."""
    with serve(tmp_path_factory.mktemp("agent-cli")) as served:
        yield served


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--emulate", "--maze", "{garbage}"], "--maze {garbage}: maze 'garbage' line 1:"),
        (["--emulate", "--maze", "gen:99:1"], "--maze gen:99:1: size must be in 1..64"),
        (["--emulate", "--world", "{garbage}"], "--world {garbage}: invalid JSON"),
        (["--emulate", "--index", "-1"], "--index: must be >= 0"),
        (["--emulate", "--connect", "garbage"], "--connect: 'garbage' is not PROTOCOL/ADDRESS"),
        (["--emulate", "--start-pose", "1,2"], "--start-pose: must be X,Y,HEADING"),
        (["--emulate", "--log-level", "LOUD"], "--log-level: unknown log level 'LOUD'"),
        (["--emulate", "--robot-id", "a b"], "--robot-id: robot id 'a b' must match"),
        (["--emulate", "--server-key", "{garbage}"], "--server-key {garbage}: not a PEM"),
        (["--emulate", "--zenoh-user", "r1"], "--zenoh-user/--zenoh-password: zenoh user and"),
        (["--tracker", "--serial", "{port}"], "--tracker: it emulates a tracker"),
        (["--serial", "{port}"], "--serial: cannot open {port}"),
        (["--emulate", "--serial", "{port}"], "--serial/--emulate: give exactly one"),
    ],
)
def test_a_bad_flag_is_one_line_before_anything_is_fetched_or_pinned(
    server: Served, tmp_path: Path, flags: list[str], named: str
) -> None:
    garbage = tmp_path / "garbage.txt"
    garbage.write_text(GARBAGE)
    values = {"garbage": str(garbage), "port": str(tmp_path / "no-such-port")}
    state = tmp_path / "state"
    args = ["agent", "--robot-id", "r1", "--state-dir", str(state), "--server", server.url]
    result = CliRunner().invoke(app, [*args, *(f.format(**values) for f in flags)])
    assert result.exit_code == 2, result.output
    assert result.output.splitlines() == [result.output.strip()], result.output  # one line
    assert result.output.startswith(f"error: {named.format(**values)}"), result.output
    assert not (state / PINNED_KEY).exists()


def reader(stream: IO[str]) -> queue.Queue[str | None]:
    """The lines of `stream` as they come (None at its end)."""
    lines: queue.Queue[str | None] = queue.Queue()

    def read() -> None:
        for line in stream:
            lines.put(line.rstrip("\n"))
        lines.put(None)

    threading.Thread(target=read, daemon=True).start()
    return lines


def agent_process(robot: str, endpoint: str, state: Path, *extra: str) -> subprocess.Popen[str]:
    """`colony agent --emulate` in its own process, taking unsigned pushes (no server here)."""
    args = ["agent", "--robot-id", robot, "--emulate", "--insecure-no-verify"]
    return subprocess.Popen(
        [*COLONY, *args, "--connect", endpoint, "--state-dir", str(state), *extra],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def test_no_router_is_logged_once_then_less_and_less_often(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    seen: list[str] = []
    with agent_process("calm", endpoint, tmp_path) as agent:
        assert agent.stderr is not None
        lines = reader(agent.stderr)
        try:
            while (line := lines.get(timeout=AGENT_WAIT)) is not None:
                seen.append(line)
                if "still no router" in line:
                    break
            agent.send_signal(signal.SIGINT)
            assert agent.wait(timeout=AGENT_WAIT) == 0
        finally:
            if agent.poll() is None:
                agent.kill()
        while (line := lines.get(timeout=AGENT_WAIT)) is not None:
            seen.append(line)
    about_router = [line for line in seen if "router" in line]
    assert len(about_router) == 2, seen
    first, reminder = about_router
    assert "WARNING" in first and f"robot calm: no router at {endpoint}; retrying" in first
    assert f"robot calm: still no router at {endpoint} after 5 s (" in reminder
    attempts = int(reminder.split("(")[1].split()[0])
    assert attempts >= 4  # tried more often than it said so
    assert not [line for line in seen if "Unable to connect" in line or "Traceback" in line]


def test_a_second_agent_of_a_robot_is_refused_with_the_first_ones_address(
    tmp_path: Path,
) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with zenoh.open(router_config(port)), zenoh.open(client_config(port)) as watcher:
        online = threading.Event()
        seen: list[zenoh.SampleKind] = []

        def on_alive(sample: zenoh.Sample) -> None:
            seen.append(sample.kind)
            online.set()

        alive = watcher.liveliness().declare_subscriber(alive_key("dup"), on_alive, history=True)
        with agent_process("dup", endpoint, tmp_path / "first") as first:
            assert first.stderr is not None
            logged = reader(first.stderr)  # drained, so its logging never waits on the pipe
            try:
                assert online.wait(WAIT)
                second = subprocess.run(
                    [*COLONY, "agent", "--robot-id", "dup", "--emulate", "--insecure-no-verify",
                     "--connect", endpoint, "--state-dir", str(tmp_path / "second"),
                     "--log-level", "ERROR"],
                    capture_output=True, text=True, timeout=WAIT,
                )  # fmt: skip
                assert second.returncode == 1, second.stderr
                assert second.stderr.splitlines() == [
                    f"error: --robot-id dup: another agent runs this robot, at "
                    f"{socket.gethostname()}:{first.pid} (HOST:PID): stop it, or give this one "
                    "another --robot-id"
                ]
                assert first.poll() is None  # the first one runs on, never seen offline
                assert zenoh.SampleKind.DELETE not in seen
                first.send_signal(signal.SIGINT)
                code = first.wait(timeout=AGENT_WAIT)
                assert code == 0, "\n".join(iter(lambda: logged.get(timeout=AGENT_WAIT), None))
            finally:
                alive.undeclare()  # type: ignore[no-untyped-call]
                if first.poll() is None:
                    first.kill()
