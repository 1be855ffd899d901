"""The REST API and its CLI clients against a real uvicorn server on a free port."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from typer.testing import CliRunner

from colony.cli import app as cli
from evorobotics.evolution import evolve
from schemas.run import RunConfig
from server.core.settings import Settings
from tests.helpers import (
    SMALL,
    WAIT,
    check_small_run,
    eventually,
    free_port,
    serving,
    wait_status,
    worker_thread,
)
from worker.main import evaluate_slice


@pytest.fixture(scope="module")
def base_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The zenoh-less mode: one in-process executor evaluates."""
    db = tmp_path_factory.mktemp("api") / "colony.db"
    settings = Settings(db_url=f"sqlite:///{db}", port=free_port(), zenoh=False)
    with serving(settings) as (url, _):
        yield url


def test_small_run_completes_and_matches_evolve(base_url: str) -> None:
    check_small_run(base_url)


def test_errors_name_the_problem(base_url: str) -> None:
    with httpx.Client(base_url=base_url, timeout=30) as client:
        bad = client.post("/api/runs", json={"population": 2})
        assert bad.status_code == 422 and "population" in bad.json()["detail"]
        unknown = client.post("/api/runs", json={"bogus": 1})
        assert unknown.status_code == 422 and "bogus" in unknown.json()["detail"]
        # JSON extensions Python's parser accepts
        for body in ('{"fitness": {"k2": NaN}}', '{"world": {"dt": Infinity}}'):
            headers = {"content-type": "application/json"}
            refused = client.post("/api/runs", content=body, headers=headers)
            assert refused.status_code == 422 and "finite" in refused.json()["detail"], body
        assert client.get("/api/runs").status_code == 200  # nothing non-finite was stored
        assert client.get("/api/runs/9999").status_code == 404
        assert client.post("/api/runs/9999/pause").status_code == 404
        assert client.get("/api/controllers/" + "0" * 64).status_code == 404
        assert client.get("/healthz").json()["status"] == "ok"


def test_lifecycle_transitions(base_url: str) -> None:
    with httpx.Client(base_url=base_url, timeout=30) as client:
        run_id = client.post("/api/runs", json={**SMALL, "generations": 10_000}).json()["id"]
        paused = client.post(f"/api/runs/{run_id}/pause")
        assert paused.status_code == 200 and paused.json()["status"] == "paused"
        assert client.post(f"/api/runs/{run_id}/pause").status_code == 409
        assert client.post(f"/api/runs/{run_id}/resume").json()["status"] == "running"
        colony = client.get("/api/colony").json()
        assert run_id in [r["id"] for r in colony["active"]]
        assert client.post(f"/api/runs/{run_id}/cancel").json()["status"] == "cancelled"
        conflict = client.post(f"/api/runs/{run_id}/resume")
        assert conflict.status_code == 409 and "cancelled" in conflict.json()["detail"]
        assert client.get("/api/colony").json()["jobs"]["pending"] == 0


def test_cli_drives_a_run(base_url: str, tmp_path: Path) -> None:
    runner = CliRunner()
    config = tmp_path / "run.json"
    config.write_text(json.dumps({**SMALL, "generations": 3}))
    started = runner.invoke(
        cli,
        ["run", "start", "--config", str(config), "--seed", "7", "--server", base_url, "--json"],
    )
    assert started.exit_code == 0, started.output
    run = json.loads(started.output)
    assert run["seed"] == 7 and run["config"]["generations"] == 3
    with httpx.Client(base_url=base_url, timeout=30) as client:
        wait_status(client, run["id"], {"completed"})
    shown = runner.invoke(cli, ["run", "show", str(run["id"]), "--server", base_url, "--json"])
    assert shown.exit_code == 0 and len(json.loads(shown.output)["history"]) == 3
    listed = runner.invoke(cli, ["run", "list", "--server", base_url])
    assert listed.exit_code == 0 and "completed" in listed.output
    status = runner.invoke(cli, ["status", "--server", base_url, "--json"])
    assert status.exit_code == 0 and "runs" in json.loads(status.output)
    refused = runner.invoke(cli, ["run", "resume", str(run["id"]), "--server", base_url])
    assert refused.exit_code == 1 and "completed" in refused.output
    invalid = runner.invoke(cli, ["run", "start", "--population", "2", "--server", base_url])
    assert invalid.exit_code == 1 and "population" in invalid.output


def broken(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    raise RuntimeError("simulated evaluator crash")


def test_a_zenoh_workers_errors_fail_no_run_the_server_evaluates_its_jobs(
    tmp_path: Path,
) -> None:
    """The only worker errs on every job: the server evaluates each job it erred on (three
    generations), the worker is quarantined at its third error in a row, and the run waits
    for an honest worker, then completes as an undisturbed run."""
    zport = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        workers=0,
    )
    with serving(settings) as (url, app), httpx.Client(base_url=url, timeout=30) as client:
        assert app.state.zenoh is not None and app.state.dispatcher is not None
        assert client.get("/api/workers").json() == []
        with worker_thread(zport, "crashy", broken):
            assert eventually(lambda: len(client.get("/api/workers").json()) == 1, WAIT)
            run_id = client.post("/api/runs", json=SMALL).json()["id"]
            assert eventually(lambda: client.get("/api/workers").json()[0]["quarantined"], WAIT)
            assert eventually(
                lambda: client.get(f"/api/runs/{run_id}").json()["generation"] == 3, WAIT
            )
            with worker_thread(zport, "honest", evaluate_slice):  # the run waited for it
                run = wait_status(client, run_id, {"completed", "failed"})
            listed = {w["name"]: w for w in client.get("/api/workers").json()}
    assert (run["status"], run["error"]) == ("completed", None)
    assert run["best_fitness"] == evolve(RunConfig(**SMALL)).history[-1].best
    crashy = listed["crashy"]
    assert crashy["jobs_done"] == 0 and crashy["quarantined"] is True
    assert "3 error results in a row" in crashy["quarantine_reason"]


def test_healthz_reports_a_stopped_loop(tmp_path: Path) -> None:
    """ok while the writer and the evaluators run; 503 naming the loop once one stops."""
    settings = Settings(db_url=f"sqlite:///{tmp_path / 'c.db'}", port=free_port(), zenoh=False)
    with serving(settings) as (url, app), httpx.Client(base_url=url) as client:
        healthy = client.get("/healthz")
        assert healthy.status_code == 200 and healthy.json()["status"] == "ok"
        app.state.manager.stop()  # its writer thread ends: runs would never be written
        sick = client.get("/healthz")
        assert sick.status_code == 503
        assert sick.json()["status"] == "unhealthy" and sick.json()["stopped"] == ["manager"]


def test_a_generation_rebuilt_while_another_is_answers_503_retry_after(base_url: str) -> None:
    """Between checkpoints a generation's individuals are simulated again; one such rebuild
    runs at a time, so open readers cannot make the server simulate on every core."""
    from server.runs import crud

    with httpx.Client(base_url=base_url, timeout=30) as client:
        run_id = client.post("/api/runs", json=SMALL).json()["id"]
        wait_status(client, run_id, {"completed"})
        url = f"/api/runs/{run_id}/individuals?generation=1"  # SMALL's checkpoint is its last
        with crud._REBUILDING:  # another reader's rebuild in progress
            busy = client.get(url)
        assert busy.status_code == 503 and busy.headers["Retry-After"] == "2"
        assert "ask again" in busy.json()["detail"]
        again = client.get(url)
        assert again.status_code == 200 and len(again.json()["individuals"]) == 12
