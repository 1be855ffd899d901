"""`colony demo` end to end in a subprocess: files, summary, and no process left behind."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.helpers import free_port


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


def test_demo_end_to_end_leaves_files_summary_and_no_process(tmp_path: Path) -> None:
    zenoh_port = free_port()
    out = tmp_path / "demo"
    args = [
        sys.executable,
        "-c",
        "from colony.cli import main; main()",
        "demo",
        "--generations",
        "5",
        "--population",
        "12",
        "--robots",
        "2",
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
    env = {**os.environ, "COLUMNS": "200"}
    done = subprocess.run(args, capture_output=True, text=True, timeout=110, env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    text = done.stdout
    for name in ("best.json", "fitness.png", "paths.png", "network.png", "responses.png"):
        assert (out / name).stat().st_size > 0, name
    assert (out / "colony.db").is_file()
    assert "5/5" in text and "completed" in text
    robot_rows = [line for line in text.splitlines() if "evbot-" in line]
    assert len(robot_rows) == 2
    for row in robot_rows:
        cells = [c.strip() for c in row.split("│") if c.strip()]
        # A 5-generation controller may be stuck and escaping at the snapshot; either way it drives.
        assert cells[1] == "yes" and cells[2] in ("running", "escaping"), row
        assert int(cells[3]) > 0, row  # the pushed controller drove it
    assert "dashboard: http://127.0.0.1:" in text
    assert processes_mentioning(f"127.0.0.1:{zenoh_port}") == []
    assert processes_mentioning(str(out)) == []
