"""`colony demo` end to end in a subprocess: files, summary, what its ending says is running
and stopped, and no process left behind; with --keep-running, a live dashboard until Ctrl-C; on
a machine whose kernels are not compiled yet, it says so."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from colony.demo import free_ports
from tests.helpers import free_port

COMPILING = "compiling the simulator, once per machine: about 15 s"


def processes_mentioning(text: str) -> list[str]:
    """Command lines of live processes (not zombies) that contain `text`."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            status = (entry / "status").read_text()
        except OSError:
            continue
        if text in cmdline and "State:\tZ" not in status:
            found.append(cmdline)
    return found


def demo_args(out: Path, zenoh_port: int, robots: int = 2) -> list[str]:
    """A small demo: 5 generations of 12, `robots` exploring 3 s, one worker."""
    return [
        sys.executable,
        "-c",
        "from colony.cli import main; main()",
        "demo",
        "--generations",
        "5",
        "--population",
        "12",
        "--robots",
        str(robots),
        "--explore-seconds",
        "3",
        "--workers",
        "1",
        "--dir",
        str(out),
        "--port",
        "0",
        "--zenoh-port",
        str(zenoh_port),
    ]


def test_demo_end_to_end_leaves_files_summary_and_no_process(tmp_path: Path) -> None:
    zenoh_port = free_port()
    out = tmp_path / "demo"
    env = {**os.environ, "COLUMNS": "200"}
    args = demo_args(out, zenoh_port)
    done = subprocess.run(args, capture_output=True, text=True, timeout=110, env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    text = done.stdout
    for name in ("best.json", "fitness.png", "paths.png", "network.png", "responses.png"):
        assert (out / name).stat().st_size > 0, name
    assert (out / "colony.db").is_file()
    assert "5/5" in text and "completed" in text
    # the bar and the ending say which number is which: training fitness, the champion's test
    assert "training fitness: best so far" in text and "last generation's best" in text
    champion = [line for line in text.splitlines() if line.startswith("champion ")]
    assert len(champion) == 1 and "training fitness" in champion[0], text
    assert "held-out test on 200 unseen poses" in text
    robot_rows = [line for line in text.splitlines() if "evbot-" in line]
    assert len(robot_rows) == 2
    for row in robot_rows:
        cells = [c.strip() for c in row.split("│") if c.strip()]
        # A 5-generation controller may be stuck and escaping at the snapshot; either way it drives.
        assert cells[1] == "yes" and cells[2] in ("running", "escaping"), row
        assert int(cells[3]) > 0, row  # the pushed controller drove it
    ending = " ".join(text[text.index("wrote ") :].split())  # rich wraps long lines
    assert "http://" not in ending  # no link to a dashboard that is gone
    hint = "the dashboard stops with the server; `colony demo --keep-running` keeps them up"
    stopped = "stopped 2 robots, then the server and its 1 worker; nothing is left running"
    assert hint in ending and stopped in ending
    assert ending.index(hint) < ending.index(stopped)
    assert processes_mentioning(f"127.0.0.1:{zenoh_port}") == []
    assert processes_mentioning(str(out)) == []


@contextmanager
def lines_of(proc: subprocess.Popen[str]) -> Iterator[queue.Queue[str | None]]:
    """`proc`'s stdout, line by line, as it prints them (None at its end)."""
    lines: queue.Queue[str | None] = queue.Queue()
    assert proc.stdout is not None
    stdout = proc.stdout

    def read() -> None:
        for line in stdout:
            lines.put(line.rstrip("\n"))
        lines.put(None)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    yield lines
    reader.join(timeout=60)


def wait_line(lines: queue.Queue[str | None], start: str, seen: list[str], timeout: float) -> str:
    """The first line beginning with `start`; lines before it go to `seen`."""
    while (line := lines.get(timeout=timeout)) is not None and not line.startswith(start):
        seen.append(line)
    assert line is not None, f"the demo ended without {start!r}: {seen}"
    return line


@pytest.mark.timeout(240)  # it compiles the kernels, as on a new machine
def test_keep_running_keeps_the_dashboard_until_ctrl_c_and_says_it_compiles(
    tmp_path: Path,
) -> None:
    """A kernel cache of its own: the kernels are compiled in this test, as on a new machine."""
    zenoh_port = free_port()
    out = tmp_path / "demo"
    env = {
        **os.environ,
        "COLUMNS": "300",
        "PYTHONUNBUFFERED": "1",
        "EVOCOLONY_KERNEL_CACHE": str(tmp_path / "kernels"),
    }
    args = [*demo_args(out, zenoh_port, robots=1), "--keep-running"]
    seen: list[str] = []
    with (
        subprocess.Popen(args, stdout=subprocess.PIPE, text=True, env=env) as demo,
        lines_of(demo) as lines,
    ):
        try:
            wait_line(lines, COMPILING, seen, timeout=60)
            up = wait_line(lines, "stopped 1 robot; still running: the server and", seen, 200)
            dashboard = up.split("dashboard ")[1].split()[0]
            assert httpx.get(dashboard, timeout=30).status_code == 200
            demo.send_signal(signal.SIGINT)
            last = wait_line(lines, "stopped the server and its 1 worker; nothing", seen, 30)
            assert last.startswith(
                "stopped the server and its 1 worker; nothing is left running; demo took"
            )
            assert demo.wait(timeout=60) == 0
        finally:  # Ctrl-C, so the demo stops its children (each in its own session)
            if demo.poll() is None:
                demo.send_signal(signal.SIGINT)
                try:
                    demo.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    demo.kill()
    assert processes_mentioning(f"127.0.0.1:{zenoh_port}") == []
    assert processes_mentioning(str(out)) == []


def test_the_demo_never_gives_its_server_and_router_one_port() -> None:
    """A free port the OS picks for one is never the other's, even when the other was free
    only because nobody held it yet (CI saw the HTTP server fail to bind the router's port)."""
    taken = free_port()
    for preferred in [(0, taken), (taken, 0), (taken, taken), (0, 0)]:
        http, zenoh = free_ports(*preferred)
        assert http != zenoh
        assert taken in (http, zenoh) or preferred == (0, 0)
