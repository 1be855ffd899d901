"""End to end: the real server app (its own zenoh router, the robot service hook) and real
`colony agent --emulate` processes: online, push, traces, replay, SIGTERM, restart from disk."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from server.core.settings import Settings
from tests.helpers import QUICK, WAIT, completed_run, eventually, free_port, serving


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str, int]]:
    """(base URL, zenoh endpoint, id of a completed run)."""
    tmp = tmp_path_factory.mktemp("e2e")
    port, zport = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    settings = Settings(
        db_url=f"sqlite:///{tmp / 'colony.db'}",
        port=port,
        zenoh_listen=[endpoint],
        workers=0,
        executors=1,
    )
    with serving(settings) as (url, _):  # the robot service is on by default
        yield url, endpoint, completed_run(url, QUICK)


def agent_process(
    robot: str, endpoint: str, state_dir: Path, url: str, *more: str
) -> subprocess.Popen[str]:
    """A real agent; it pins the server's signing key from `url` on first start."""
    colony = str(Path(sys.executable).with_name("colony"))
    args = ["--robot-id", robot, "--emulate", "--maze", "paper", "--seed", "1", "--server", url]
    args += ["--connect", endpoint, "--state-dir", str(state_dir), "--log-level", "WARNING"]
    args += more
    return subprocess.Popen(
        [colony, "agent", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def robot(client: httpx.Client, robot_id: str) -> dict[str, Any] | None:
    response = client.get(f"/api/robots/{robot_id}")
    return response.json() if response.status_code == 200 else None


def test_emulated_agent_process_end_to_end(server: tuple[str, str, int], tmp_path: Path) -> None:
    url, endpoint, run_id = server
    proc = agent_process("e2e", endpoint, tmp_path, url)
    try:
        with httpx.Client(base_url=url, timeout=30) as client:
            assert eventually(lambda: (robot(client, "e2e") or {}).get("online") is True)
            pushed = client.post("/api/robots/e2e/controller", json={"run_id": run_id}).json()
            assert pushed["acknowledged"] and pushed["accepted"], pushed
            best = client.get(f"/api/runs/{run_id}/best").json()  # the run's champion
            assert pushed["sha256"] == best["sha256"] and best["validation"] is not None
            assert eventually(lambda: client.get("/api/robots/e2e/replay").json()["checked"] >= 20)
            replay = client.get("/api/robots/e2e/replay").json()
            assert replay["identical"], replay

            def field() -> dict[str, Any] | None:
                doc = client.get(f"/api/controllers/{pushed['sha256']}").json()
                return doc["field"]  # type: ignore[no-any-return]

            assert eventually(lambda: (field() or {}).get("robot_hours", 0) > 0)
            detail = robot(client, "e2e")
            assert detail is not None and detail["controller_sha256"] == pushed["sha256"]
            assert detail["controller_rank"] == best["validation"]["training_rank"]
            assert detail["boot"] == 0

            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=WAIT)
            assert proc.returncode == 0, err
            assert "samples delivered" in out
            assert eventually(lambda: (robot(client, "e2e") or {}).get("online") is False, 10)

            proc = agent_process(
                "e2e", endpoint, tmp_path, url
            )  # restarts with the saved controller
            assert eventually(lambda: (robot(client, "e2e") or {}).get("boot") == 1)
            detail = robot(client, "e2e")
            assert detail is not None and detail["online"]
            assert detail["controller_sha256"] == pushed["sha256"]
            assert detail["state"] == "running"
    finally:
        proc.terminate()
        proc.communicate(timeout=WAIT)


def test_an_emulated_agent_with_a_tracker_stores_the_trackers_poses(
    server: tuple[str, str, int], tmp_path: Path
) -> None:
    """`colony agent --emulate --tracker`: the firmware cannot tell the agent its pose (as a
    real BasicX), the emulated tracker publishes it, and the server stores it with the traces."""
    url, endpoint, run_id = server
    proc = agent_process("e2e-t", endpoint, tmp_path, url, "--tracker")
    try:
        with httpx.Client(base_url=url, timeout=30) as client:
            assert eventually(lambda: (robot(client, "e2e-t") or {}).get("online") is True)
            pushed = client.post("/api/robots/e2e-t/controller", json={"run_id": run_id}).json()
            assert pushed["accepted"], pushed

            def sources() -> set[str]:
                traces = client.get("/api/robots/e2e-t/traces", params={"limit": 20}).json()
                samples = traces["samples"]
                return {s["pose_source"] for s in samples} if len(samples) == 20 else set()

            assert eventually(lambda: sources() == {"tracker"})
    finally:
        proc.terminate()
        proc.communicate(timeout=WAIT)
