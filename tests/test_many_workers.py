"""Many workers: 24 `colony worker` processes on loopback, with a lab's credentials (`colony
lab init`: three worker credentials, eight processes under each as USER.i), take a study's
jobs from one `colony server`; every run's champion is `colony evolve`'s, bit for bit.

Each generation is cut into as many jobs as there are workers (spans off), so every process
evaluates; the study is small (three runs of tiny generations). On 2 cores the workers take
about 20 s to start and 15 s more to load their compiled kernels and end the study (about 40
s in all). A worker process (numpy, numba's cached kernels, zenoh) holds about 90 MB of its
own: the 24 need about 2.2 GB, checked against what the machine has before any starts.
"""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from schemas.run import RunConfig
from server.core.lab import init_lab
from tests.helpers import COLONY, Processes, evolved_champion, free_port, wait_until

pytestmark = pytest.mark.slow  # it starts 25 processes

WORKERS = 24
CREDENTIALS = ("wa", "wb", "wc")
"""Each credential serves WORKERS / 3 processes, named USER.0, USER.1, ..."""
WORKER_MB = 100
"""A worker process's memory after its first jobs (measured: 89 MB proportional set size;
240 MB resident, counting in full the libraries all the workers share)."""
BASE: dict[str, Any] = {
    "population": 48,
    "job_size": 2,
    "generations": 3,
    "trials": 1,
    "steps": 20,
    "validation": {"poses": 4, "steps": 20, "candidates": 8, "test_poses": 8},
}
"""Jobs of two individuals: a generation is 24 jobs, one a worker."""
SEEDS = [0, 1, 2]
TIMEOUT_S = 90.0


def read_env(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line)


def available_mb() -> int:
    """MemAvailable of /proc/meminfo, in MB."""
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) // 1024
    raise RuntimeError("no MemAvailable in /proc/meminfo")


def pss_mb(pid: int) -> float:
    """A process's proportional share of memory (its own pages, and its share of those it
    shares with others: the libraries every worker maps), in MB; 0 once it is gone."""
    try:
        rollup = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except FileNotFoundError:
        return 0.0
    for line in rollup.splitlines():
        if line.startswith("Pss:"):
            return int(line.split()[1]) / 1024
    return 0.0


class LabColony(Processes):
    """A lab's server and workers as subprocesses; every one is killed and reaped at the end."""

    def __init__(self, tmp: Path) -> None:
        self.zenoh = free_port()
        self.http = free_port()
        lab = init_lab(
            tmp / "lab", workers=CREDENTIALS, robots=(), server_host="127.0.0.1", port=self.zenoh
        )
        self.server_env = read_env(lab.server_env)
        self.worker_envs = {name: read_env(path) for name, path in lab.worker_envs.items()}
        token = self.server_env["COLONY_API_TOKEN"]
        client = httpx.Client(
            base_url=f"http://127.0.0.1:{self.http}",
            headers={"Authorization": f"Bearer {token}"},
            timeout=30,
        )
        super().__init__(tmp, client)

    def start_server(self) -> None:
        argv = [*COLONY, "server", "--db", f"sqlite:///{self.tmp / 'colony.db'}"]
        argv += ["--port", str(self.http), "--workers", "0"]
        env = {
            **self.server_env,
            "COLONY_HOST": "127.0.0.1",
            "COLONY_ZENOH_LISTEN": f'["tcp/127.0.0.1:{self.zenoh}"]',
            "COLONY_SPAN_BELOW_SECONDS": "0",  # slices: every worker evaluates
            "COLONY_HOUSEKEEPING_SECONDS": "0.2",
        }
        server = self.spawn(argv, env, "server")
        wait_until(lambda: self.healthy(server), "server health", TIMEOUT_S, tick=0.5)

    def start_workers(self) -> list[subprocess.Popen[bytes]]:
        per = WORKERS // len(CREDENTIALS)
        started = []
        for user, env in self.worker_envs.items():
            for i in range(per):
                argv = [
                    *COLONY,
                    "worker",
                    "--connect",
                    env["COLONY_CONNECT"],
                    "--name",
                    f"{user}.{i}",
                ]
                started.append(self.spawn(argv, env, f"{user}.{i}"))
        return started

    def idle_workers(self) -> int:
        return sum(w["state"] == "idle" for w in self.get("/api/workers"))


@pytest.fixture
def colony(tmp_path: Path) -> Iterator[LabColony]:
    c = LabColony(tmp_path)
    try:
        yield c
    finally:
        c.close()


def test_24_authenticated_workers_run_a_study_whose_champions_are_evolves(
    colony: LabColony,
) -> None:
    if available_mb() < 2 * WORKERS * WORKER_MB:
        pytest.skip(f"{WORKERS} worker processes need about {WORKERS * WORKER_MB} MB")
    colony.start_server()
    workers = colony.start_workers()
    wait_until(
        lambda: colony.idle_workers() == WORKERS,
        f"{WORKERS} workers asking for jobs",
        TIMEOUT_S,
        tick=0.5,
    )
    created = colony.client.post(
        "/api/studies", json={"name": "many", "base": BASE, "seeds": SEEDS}
    )
    assert created.is_success, created.text
    study = created.json()
    wait_until(
        lambda: colony.get(f"/api/studies/{study['id']}")["status"] == "completed",
        "the study's end",
        TIMEOUT_S,
        tick=0.5,
    )
    runs = colony.get(f"/api/studies/{study['id']}")["runs"]
    assert sorted(r["seed"] for r in runs) == SEEDS
    for run in runs:
        assert run["status"] == "completed"
        config = RunConfig.model_validate({**BASE, "seed": run["seed"]})
        served = colony.client.get(f"/api/runs/{run['run_id']}/best").text
        assert served == evolved_champion(config, run["run_id"]).to_json()
    listed = {w["name"]: w for w in colony.get("/api/workers")}
    assert len(listed) == WORKERS
    assert all(w["jobs_done"] > 0 for w in listed.values())  # every process took jobs
    assert sum(pss_mb(p.pid) for p in workers) < 2 * WORKERS * WORKER_MB
