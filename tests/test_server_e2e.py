"""`colony server` killed with SIGKILL mid-run resumes and ends bit-identical to `evolve`."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from evorobotics.evolution import evolve
from schemas.run import RunConfig
from server.runs import crud
from tests.helpers import free_port

CONFIG = {"population": 12, "generations": 1200, "steps": 20, "job_size": 5, "seed": 3}
"""Generations of about a millisecond: with spans, enough of them to be killed mid-run (the
progress the server shows moves over about a second; with 400 it finished once under the
whole suite's load before a poll saw it running past generation 2)."""
TIMEOUT_S = 90.0


@contextmanager
def colony_server(db: Path, port: int) -> Iterator[subprocess.Popen[bytes]]:
    """`colony server` with its default local workers, zenoh on a free loopback port."""
    colony = Path(sys.executable).parent / "colony"
    argv = [str(colony), "server", "--db", f"sqlite:///{db}", "--port", str(port)]
    argv += ["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"]
    proc = subprocess.Popen(
        argv,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "COLONY_HOUSEKEEPING_SECONDS": "0.2"},
    )
    try:
        deadline = time.monotonic() + TIMEOUT_S
        with httpx.Client(timeout=1) as probe:
            while True:
                try:
                    if probe.get(f"http://127.0.0.1:{port}/healthz").is_success:
                        break
                except httpx.TransportError:
                    pass
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("colony server did not start")
                threading.Event().wait(0.05)
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
        proc.wait(timeout=30)


def wait_for(client: httpx.Client, url: str, predicate: Any) -> dict[str, Any]:
    """Poll `url` with one client (`httpx.get` would build one per call: 35 ms of CPU each,
    at 50 polls a second a core taken from the server under test)."""
    deadline = time.monotonic() + TIMEOUT_S
    while time.monotonic() < deadline:
        run: dict[str, Any] = client.get(url, timeout=5).json()
        if predicate(run):
            return run
        threading.Event().wait(0.02)
    raise TimeoutError(f"{url} never satisfied the condition")


def population_hash(db: Path, run_id: int, generation: int) -> str:
    """sha256 of the generation's genome bytes in rank order (a copy's read from its origin)."""
    engine = sa.create_engine(f"sqlite:///{db}")
    with Session(engine) as session:
        genomes = crud.ranked(session, run_id=run_id, generation=generation)[1]
    engine.dispose()
    return hashlib.sha256(genomes.tobytes()).hexdigest()


@pytest.mark.slow
def test_sigkill_mid_run_then_restart_is_bit_identical(tmp_path: Path) -> None:
    db = tmp_path / "colony.db"
    port = free_port()
    with httpx.Client(timeout=10) as client:
        with colony_server(db, port) as proc:
            base = f"http://127.0.0.1:{port}"
            run_id = client.post(f"{base}/api/runs", json=CONFIG).json()["id"]
            at = f"{base}/api/runs/{run_id}"
            killed_at = wait_for(client, at, lambda r: r["generation"] >= 2)
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=30)
        assert killed_at["status"] == "running"
        port = free_port()
        with colony_server(db, port):
            base = f"http://127.0.0.1:{port}"
            after = client.get(f"{base}/api/runs/{run_id}").json()
            assert after["generation"] < CONFIG["generations"], "the run finished before the kill"
            run = wait_for(client, f"{base}/api/runs/{run_id}", lambda r: r["status"] != "running")
            assert run["status"] == "completed", run["error"]
            best = client.get(f"{base}/api/runs/{run_id}/best").json()
            history = client.get(f"{base}/api/runs/{run_id}/generations").json()
    local = evolve(RunConfig(**CONFIG))
    assert [g["generation"] for g in history] == list(range(CONFIG["generations"]))
    assert [g["best"] for g in history] == [h.best for h in local.history]
    assert best["sha256"] == local.best.sha256
    assert local.state.ranked is not None
    expected = hashlib.sha256(local.state.ranked.tobytes()).hexdigest()
    assert population_hash(db, run_id, CONFIG["generations"] - 1) == expected
