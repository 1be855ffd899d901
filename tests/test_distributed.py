"""Real processes on loopback: `colony server` on a temp SQLite file, `colony worker`s over zenoh.

Every run must end with the same best controller as `evolve` for the same config and seed,
and with exactly population x generations evaluations (a duplicate result never counts), no
matter which worker is killed, stopped, added, or whether the server itself is SIGKILLed.
"""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterator
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import pytest

from evorobotics.evolution import evolve
from schemas.run import RunConfig
from tests.helpers import COLONY, Processes, free_port, wait_until

CONFIG = {"population": 16, "job_size": 4, "generations": 6, "steps": 2000, "seed": 11}
"""Jobs of tens of milliseconds, so a worker is caught holding one. Under the reality gap (the
default), so every kill, restart and span below also checks that the gap draws do not depend
on who evaluated what."""
EVALUATIONS = 16 * 6


@pytest.fixture(scope="module")
def expected_sha() -> str:
    return evolve(RunConfig(**CONFIG)).best.sha256


class Colony(Processes):
    """A server and workers as subprocesses; every one is killed and reaped at the end."""

    def __init__(self, tmp: Path) -> None:
        self.db = tmp / "colony.db"
        self.http = free_port()
        self.zenoh = free_port()
        self.server: subprocess.Popen[bytes] | None = None
        # One client: `httpx.get` builds one per call (35 ms of CPU, at 50 polls a second
        # a core taken from the server and workers under test).
        super().__init__(tmp, httpx.Client(base_url=f"http://127.0.0.1:{self.http}", timeout=10))

    def start_server(
        self, workers: int = 0, *, spans: bool = False, **env: str
    ) -> subprocess.Popen[bytes]:
        """`spans`: every generation with a measured worker speed goes out as a span of the
        rest of the run, evolved by one worker; otherwise generations are cut into parallel
        slices."""
        argv = [
            *COLONY,
            "server",
            "--db",
            f"sqlite:///{self.db}",
            "--port",
            str(self.http),
            "--zenoh-listen",
            f"tcp/127.0.0.1:{self.zenoh}",
            "--workers",
            str(workers),
        ]
        spanning = {
            "COLONY_SPAN_BELOW_SECONDS": "10",
            "COLONY_SPAN_SECONDS": "600",
        }
        off = {"COLONY_SPAN_BELOW_SECONDS": "0"}
        env = {"COLONY_HOUSEKEEPING_SECONDS": "0.2", **(spanning if spans else off), **env}
        self.server = self.spawn(argv, env, "server")
        wait_until(partial(self.healthy, self.server), "server health")
        return self.server

    def start_worker(self, name: str) -> subprocess.Popen[bytes]:
        connect = f"tcp/127.0.0.1:{self.zenoh}"
        return self.spawn([*COLONY, "worker", "--connect", connect, "--name", name], {}, name)

    def post(self, path: str, body: Any = None) -> Any:
        response = self.client.post(path, json=body)
        assert response.is_success, response.text
        return response.json()

    def workers(self) -> dict[str, dict[str, Any]]:
        return {w["name"]: w for w in self.get("/api/workers")}

    def finished(self, run_id: int) -> bool:
        return self.run(run_id)["status"] in ("completed", "failed")

    def run(self, run_id: int) -> dict[str, Any]:
        run: dict[str, Any] = self.get(f"/api/runs/{run_id}")
        return run

    def finish(
        self, run_id: int, expected_sha: str, evaluations: int = EVALUATIONS
    ) -> dict[str, Any]:
        """Wait for the run's end; check it matches evolve and counted every job once."""
        wait_until(partial(self.finished, run_id), "run end")
        run = self.run(run_id)
        assert run["status"] == "completed", run["error"]
        assert run["evaluations"] == evaluations
        assert self.get(f"/api/runs/{run_id}/best")["sha256"] == expected_sha
        return run


@pytest.fixture
def colony(tmp_path: Path) -> Iterator[Colony]:
    c = Colony(tmp_path)
    try:
        yield c
    finally:
        c.close()


def exited(pid: int) -> bool:
    """True once `pid` is gone or a zombie (a reparented orphan may wait to be reaped)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return True
    return "\nState:\tZ" in status


def local_pids(colony: Colony, count: int) -> list[int]:
    """Pids of the server's local workers: their default names end in -pid."""
    wait_until(lambda: len(colony.workers()) == count, f"{count} local workers")
    return [int(name.rsplit("-", 1)[1]) for name in colony.workers()]


def test_two_local_workers_finish_a_run_and_stop_with_the_server(
    colony: Colony, expected_sha: str
) -> None:
    server = colony.start_server(workers=2)
    pids = local_pids(colony, 2)
    cores = str(len(os.sched_getaffinity(0)))
    for pid in pids:  # each evaluates on every core: a run's span then has them all
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
        assert argv[argv.index("--threads") + 1] == cores
    run_id = colony.post("/api/runs", CONFIG)["id"]
    colony.finish(run_id, expected_sha)
    workers = colony.workers()
    # both workers were live before the run: each evaluates on every core, so a generation is
    # one job of one of them (on one core, cut in two), and its champion's validation and test
    # are cut in two
    per_generation = 1 if int(cores) > 1 else 2
    assert sum(w["jobs_done"] for w in workers.values()) == 6 * per_generation + 2 * 2
    assert all(w["robot_steps_per_s"] and w["state"] == "idle" for w in workers.values())
    assert len(colony.get("/api/colony")["workers"]) == 2
    server.send_signal(signal.SIGTERM)
    # uvicorn shuts the app down, then re-raises the signal it caught.
    assert server.wait(timeout=30) in (0, -signal.SIGTERM)
    assert all(exited(pid) for pid in pids)


def test_sigkilled_server_leaves_no_orphan_workers(colony: Colony) -> None:
    server = colony.start_server(workers=1)
    [pid] = local_pids(colony, 1)
    server.kill()
    server.wait(timeout=10)
    wait_until(lambda: exited(pid), "the orphaned worker to exit", timeout=15)


def test_sigkilled_worker_loses_no_job_and_a_late_joiner_takes_jobs(colony: Colony) -> None:
    config = {**CONFIG, "generations": 30}  # generations left after the pause, at any speed
    colony.start_server()
    doomed = colony.start_worker("doomed")
    colony.start_worker("steady")
    wait_until(lambda: len(colony.workers()) == 2, "two workers")
    run_id = colony.post("/api/runs", config)["id"]
    wait_until(lambda: colony.workers()["doomed"]["state"] == "busy", "doomed busy")
    doomed.kill()
    colony.post(f"/api/runs/{run_id}/pause")
    wait_until(lambda: colony.run(run_id)["status"] == "paused", "the pause")
    colony.start_worker("late")
    wait_until(lambda: "late" in colony.workers(), "the late worker")
    colony.post(f"/api/runs/{run_id}/resume")
    colony.finish(run_id, evolve(RunConfig(**config)).best.sha256, evaluations=16 * 30)
    workers = colony.workers()
    assert workers["doomed"]["state"] == "gone"
    assert workers["late"]["jobs_done"] > 0


def test_stopped_worker_past_its_lease_is_replaced_and_its_late_result_dropped(
    colony: Colony, expected_sha: str
) -> None:
    colony.start_server(COLONY_LEASE_MIN_SECONDS="0.5", COLONY_LEASE_UNKNOWN_SECONDS="20")
    hung = colony.start_worker("hung")
    run_id = colony.post("/api/runs", CONFIG)["id"]
    wait_until(
        lambda: (
            (w := colony.workers().get("hung")) is not None
            and w["jobs_done"] >= 1
            and w["state"] == "busy"
        ),
        "hung busy with a measured speed",
    )
    hung.send_signal(signal.SIGSTOP)
    stopped = colony.workers()["hung"]
    at_stop, held = stopped["jobs_done"], stopped["state"] == "busy"
    colony.start_worker("rescuer")
    try:
        colony.finish(run_id, expected_sha)
        # A result sent just before the stop arrives on time and counts: read after the run.
        done_before = colony.workers()["hung"]["jobs_done"]
    finally:
        hung.send_signal(signal.SIGCONT)
    assert colony.workers()["rescuer"]["jobs_done"] > 0
    # The woken worker delivers the result of the job it held: dropped as late, never counted
    # (unless it held none: its last result beat the stop).
    wait_until(
        lambda: colony.workers()["hung"]["late"] > 0 or done_before > at_stop or not held,
        "the late result",
    )
    assert colony.workers()["hung"]["jobs_done"] == done_before
    assert colony.run(run_id)["evaluations"] == EVALUATIONS


LONG_CONFIG = {**CONFIG, "generations": 12}
"""Long enough that the server is still evolving it when killed (at generation 2, ten to go):
told generations are written together (server.runs.lifecycle.WRITE_AFTER_S), several at once."""


def test_sigkilled_server_restarts_and_workers_reconnect_by_themselves(colony: Colony) -> None:
    expected = evolve(RunConfig(**LONG_CONFIG)).best.sha256
    server = colony.start_server()
    colony.start_worker("one")
    colony.start_worker("two")
    run_id = colony.post("/api/runs", LONG_CONFIG)["id"]
    wait_until(lambda: colony.run(run_id)["generation"] >= 2, "generation 2")
    server.kill()
    server.wait(timeout=10)
    colony.start_server()
    resumed = colony.run(run_id)
    assert resumed["status"] == "running" and resumed["generation"] < 12, resumed
    colony.finish(run_id, expected, evaluations=16 * 12)
    assert {"one", "two"} <= set(colony.workers())


SPAN_GENERATIONS = 150
SPAN_CONFIG = {"population": 16, "generations": SPAN_GENERATIONS, "steps": 300, "seed": 12}
"""Generations of a few milliseconds: far below the span threshold the span tests set; a
hundred and more left when a test interferes at generation 5."""


@pytest.fixture(scope="module")
def span_sha() -> str:
    return evolve(RunConfig(**SPAN_CONFIG)).best.sha256


def span_holder(colony: Colony, run_id: int) -> tuple[str, dict[str, dict[str, Any]]]:
    """Once the run is a few generations in: the worker evolving it alone, and the table."""
    wait_until(lambda: colony.run(run_id)["generation"] >= 5, "generation 5")
    workers = colony.workers()
    holder = max(workers, key=lambda name: workers[name]["jobs_done"])
    # generation 0 went out in slices (no speed measured yet); every later one to the holder
    assert all(w["jobs_done"] <= 1 for name, w in workers.items() if name != holder), workers
    return holder, workers


def test_a_span_s_worker_sigkilled_mid_span_hands_the_run_over(
    colony: Colony, span_sha: str
) -> None:
    colony.start_server(spans=True)
    procs = {name: colony.start_worker(name) for name in ("a", "b")}
    wait_until(lambda: len(colony.workers()) == 2, "two workers")
    run_id = colony.post("/api/runs", SPAN_CONFIG)["id"]
    holder, before = span_holder(colony, run_id)
    procs[holder].kill()
    colony.finish(run_id, span_sha, evaluations=16 * SPAN_GENERATIONS)
    after = colony.workers()
    [other] = set(procs) - {holder}
    assert after[holder]["state"] == "gone"
    assert after[other]["jobs_done"] > before[other]["jobs_done"]


def test_a_span_s_worker_stopped_past_its_lease_is_replaced_and_its_late_results_dropped(
    colony: Colony, span_sha: str
) -> None:
    colony.start_server(spans=True, COLONY_LEASE_MIN_SECONDS="0.5")
    hung = colony.start_worker("hung")
    run_id = colony.post("/api/runs", SPAN_CONFIG)["id"]
    span_holder(colony, run_id)
    hung.send_signal(signal.SIGSTOP)
    colony.start_worker("rescuer")
    try:
        # once the rescuer evolves, every result the hung worker sent before it stopped is in
        wait_until(lambda: colony.workers().get("rescuer", {}).get("jobs_done", 0) >= 3, "rescue")
        done_before = colony.workers()["hung"]["jobs_done"]
        colony.finish(run_id, span_sha, evaluations=16 * SPAN_GENERATIONS)
    finally:
        hung.send_signal(signal.SIGCONT)
    woke = datetime.now(UTC)
    wait_until(
        lambda: datetime.fromisoformat(colony.workers()["hung"]["last_seen"]) >= woke,
        "the late results",
    )
    assert colony.workers()["hung"]["jobs_done"] == done_before
    assert colony.run(run_id)["evaluations"] == 16 * SPAN_GENERATIONS


def test_a_server_sigkilled_mid_span_resumes_it_with_the_same_workers(
    colony: Colony, span_sha: str
) -> None:
    server = colony.start_server(spans=True)
    colony.start_worker("one")
    colony.start_worker("two")
    wait_until(lambda: len(colony.workers()) == 2, "two workers")
    run_id = colony.post("/api/runs", SPAN_CONFIG)["id"]
    span_holder(colony, run_id)
    server.kill()
    server.wait(timeout=10)
    colony.start_server(spans=True)
    colony.finish(run_id, span_sha, evaluations=16 * SPAN_GENERATIONS)
    assert {"one", "two"} <= set(colony.workers())
