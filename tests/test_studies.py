"""Studies through the REST API (real uvicorn, SQLite in a temp dir, in-process executors):
creation and its refusals, runs named and tagged, status, cancel, delete, statistics, and each
champion bit-identical to `colony evolve`'s."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from evorobotics.evolution import evolve
from evorobotics.stats import METRICS
from schemas.run import RunConfig
from server.core.settings import Settings
from tests.helpers import eventually, free_port, serving, worker_thread

TINY: dict[str, Any] = {
    "population": 6,
    "generations": 3,
    "steps": 5,
    "trials": 1,
    "job_size": 2,
    "validation": {"poses": 4, "steps": 50, "candidates": 3},
}
"""A run of about a second, validated on a few short trials."""
LONG = {**TINY, "generations": 10_000}
"""A run that lives until it is cancelled."""
MAX_STEPS = 100_000
"""The server's limit of robot steps per generation in these tests."""


@pytest.fixture(scope="module")
def url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    db = tmp_path_factory.mktemp("studies") / "colony.db"
    settings = Settings(
        db_url=f"sqlite:///{db}",
        port=free_port(),
        zenoh=False,
        executors=2,
        max_active_runs=2,
        max_generation_steps=MAX_STEPS,
    )
    with serving(settings) as (base, _):
        yield base


def study_status(client: httpx.Client, study_id: int, status: str) -> bool:
    return bool(client.get(f"/api/studies/{study_id}").json()["status"] == status)


def test_a_study_runs_its_conditions_and_seeds_as_evolve_would(url: str) -> None:
    conditions: dict[str, dict[str, Any]] = {"paper-best": {}, "reactive": {"network": "reactive"}}
    body = {"name": "delays", "base": TINY, "conditions": conditions, "seeds": [3, 4]}
    with httpx.Client(base_url=url, timeout=60) as client:
        created = client.post("/api/studies", json=body)
        assert created.status_code == 201, created.text
        study = created.json()
        assert study["status"] == "running" and study["finished_at"] is None
        assert study["conditions"] == {"paper-best": {}, "reactive": {"network": "reactive"}}
        assert study["seeds"] == [3, 4] and study["base"]["population"] == 6
        assert [(r["condition"], r["seed"], r["name"]) for r in study["runs"]] == [
            ("paper-best", 3, "delays/paper-best/3"),
            ("paper-best", 4, "delays/paper-best/4"),
            ("reactive", 3, "delays/reactive/3"),
            ("reactive", 4, "delays/reactive/4"),
        ]
        assert all(set(r["metrics"]) == set(METRICS) for r in study["runs"])
        for listed in study["runs"]:
            run = client.get(f"/api/runs/{listed['run_id']}").json()
            assert run["name"] == listed["name"] and run["tags"] == ["study:delays"]
            assert (run["study_id"], run["condition"]) == (study["id"], listed["condition"])
            assert run["config"]["seed"] == listed["seed"] == run["seed"]
        assert eventually(lambda: study_status(client, study["id"], "completed"), 120)
        assert eventually(
            lambda: all(
                None not in r["metrics"].values()
                for r in client.get(f"/api/studies/{study['id']}").json()["runs"]
            ),
            120,
        )
        done = client.get(f"/api/studies/{study['id']}").json()
        assert client.get("/api/studies").json()[0]["id"] == study["id"]  # newest first
        bests = {
            r["run_id"]: client.get(f"/api/runs/{r['run_id']}/best").json() for r in done["runs"]
        }
        champions = {run_id: best["sha256"] for run_id, best in bests.items()}
    assert done["finished_at"] is not None
    for run in done["runs"]:  # the champion's held-out test under the gap
        gap = bests[run["run_id"]]["test"]["gap"]
        assert run["metrics"]["gap_roaming"] == gap["roaming"]["value"]
        assert run["metrics"]["gap_stuck"] == gap["stuck"]["value"]
    for run in done["runs"]:
        config = RunConfig.model_validate(
            {**TINY, **conditions[run["condition"]], "seed": run["seed"]}
        )
        assert champions[run["run_id"]] == evolve(config).best.sha256, run["name"]
    assert [s["condition"] for s in done["summary"]] == ["paper-best", "reactive"]
    for summary in done["summary"]:
        assert summary["runs"] == summary["completed"] == 2
        assert [g["generation"] for g in summary["generations"]] == [0, 1, 2]
        assert all(g["best"]["n"] == g["mean"]["n"] == 2 for g in summary["generations"])
        assert set(summary["final"]) == set(METRICS)
        assert all(s["n"] == summary["completed"] for s in summary["final"].values())
        best = [
            r["metrics"]["best_fitness"]
            for r in done["runs"]
            if r["condition"] == summary["condition"]
        ]
        assert summary["final"]["best_fitness"]["median"] == pytest.approx(sum(best) / 2)
        last = summary["generations"][-1]["best"]
        assert last["median"] == summary["final"]["best_fitness"]["median"]
    assert {c["metric"] for c in done["comparisons"]} <= set(METRICS)
    assert all((c["a"], c["b"]) == ("paper-best", "reactive") for c in done["comparisons"])
    assert len(done["verdicts"]) == 1 and "paper-best" in done["verdicts"][0]


def test_a_grid_expands_to_named_conditions(url: str) -> None:
    body = {"name": "grid", "base": LONG, "grid": {"ga.eta": [0.5, 1.0]}, "seeds": [1]}
    with httpx.Client(base_url=url, timeout=60) as client:
        created = client.post("/api/studies", json=body)
        assert created.status_code == 201, created.text
        study = created.json()
        assert study["conditions"] == {
            "ga.eta=0.5": {"ga": {"eta": 0.5}},
            "ga.eta=1.0": {"ga": {"eta": 1.0}},
        }
        runs = [client.get(f"/api/runs/{r['run_id']}").json() for r in study["runs"]]
        assert [r["config"]["ga"]["eta"] for r in runs] == [0.5, 1.0]
        assert client.delete(f"/api/studies/{study['id']}").status_code == 204


@pytest.mark.parametrize(
    ("body", "named"),
    [
        ({"conditions": {"small": {"population": 2}}}, "small: population"),
        ({"conditions": {"odd": {"bogus": 1}}}, "odd: bogus"),
        ({"conditions": {"seeded": {"seed": 5}}}, "seeded: seed"),
        ({"base": {"seed": 5}}, "base: seed"),
        ({"seeds": []}, "seeds"),
        ({"seeds": [1, 1]}, "distinct"),
        ({"seeds": [-1]}, "seeds"),
        ({"conditions": {"a b": {}}}, "'a b'"),
        ({"grid": {"network": ["reactive", "nope"]}}, "network=nope: unknown network preset"),
        ({"grid": {"network": ["reactive", "paper-best"]}, "seeds": list(range(501))}, "1002 runs"),
        ({"conditions": {"huge": {"steps": MAX_STEPS}}}, "conditions.huge: population x trials"),
        ({"conditions": {"a": {}}, "grid": {"trials": [1]}}, "not both"),
        ({"name": "no/slash"}, "name"),
    ],
)
def test_an_invalid_study_is_refused_naming_the_problem_and_creates_nothing(
    url: str, body: dict[str, Any], named: str
) -> None:
    with httpx.Client(base_url=url, timeout=60) as client:
        studies = client.get("/api/studies").json()
        runs = client.get("/api/runs", params={"limit": 1000}).json()
        refused = client.post(
            "/api/studies", json={"name": "bad", "base": TINY, "seeds": [1], **body}
        )
        assert refused.status_code == 422, refused.text
        detail = refused.json()["detail"]
        assert named in detail and "\n" not in detail
        assert client.get("/api/studies").json() == studies
        assert client.get("/api/runs", params={"limit": 1000}).json() == runs


def test_a_study_name_is_taken_once(url: str) -> None:
    body = {"name": "twice", "base": LONG, "seeds": [1]}
    with httpx.Client(base_url=url, timeout=60) as client:
        first = client.post("/api/studies", json=body)
        assert first.status_code == 201 and first.json()["conditions"] == {"base": {}}
        again = client.post("/api/studies", json=body)
        assert again.status_code == 409 and "twice" in again.json()["detail"]
        assert client.delete(f"/api/studies/{first.json()['id']}").status_code == 204


def test_cancel_stops_the_unfinished_runs_and_delete_removes_the_study(url: str) -> None:
    with httpx.Client(base_url=url, timeout=60) as client:
        study = client.post(
            "/api/studies", json={"name": "long", "base": LONG, "seeds": [1, 2, 3]}
        ).json()
        ids = [r["run_id"] for r in study["runs"]]
        statuses = [client.get(f"/api/runs/{i}").json()["status"] for i in ids]
        assert "queued" in statuses  # beyond max_active_runs they queue as usual
        cancelled = client.post(f"/api/studies/{study['id']}/cancel")
        assert cancelled.status_code == 200
        assert cancelled.json()["status"] == "cancelled"
        assert cancelled.json()["finished_at"] is not None
        assert {r["status"] for r in cancelled.json()["runs"]} == {"cancelled"}
        assert client.get("/api/colony").json()["jobs"]["pending"] == 0
        assert client.delete(f"/api/studies/{study['id']}").status_code == 204
        assert client.get(f"/api/studies/{study['id']}").status_code == 404
        assert all(client.get(f"/api/runs/{i}").status_code == 404 for i in ids)
        assert client.delete(f"/api/studies/{study['id']}").status_code == 404
        assert client.post(f"/api/studies/{study['id']}/cancel").status_code == 404


def test_a_study_ends_cancelled_when_its_runs_are_cancelled_one_by_one(url: str) -> None:
    with httpx.Client(base_url=url, timeout=60) as client:
        study = client.post(
            "/api/studies", json={"name": "one-by-one", "base": LONG, "seeds": [1, 2]}
        ).json()
        first, second = (r["run_id"] for r in study["runs"])
        assert client.post(f"/api/runs/{first}/cancel").status_code == 200
        assert study_status(client, study["id"], "running")
        assert client.post(f"/api/runs/{second}/cancel").status_code == 200
        assert study_status(client, study["id"], "cancelled")
        assert client.delete(f"/api/runs/{first}").status_code == 204
        left = client.get(f"/api/studies/{study['id']}").json()
        assert [r["run_id"] for r in left["runs"]] == [second]
        assert client.delete(f"/api/studies/{study['id']}").status_code == 204


def test_a_live_study_is_deleted_with_its_runs(url: str) -> None:
    with httpx.Client(base_url=url, timeout=60) as client:
        study = client.post(
            "/api/studies", json={"name": "doomed", "base": LONG, "seeds": [1, 2]}
        ).json()
        assert client.delete(f"/api/studies/{study['id']}").status_code == 204
        assert all(client.get(f"/api/runs/{r['run_id']}").status_code == 404 for r in study["runs"])
        assert client.get("/api/colony").json()["jobs"]["pending"] == 0
        after = client.post("/api/runs", json=TINY).json()  # the server keeps running runs
        assert eventually(
            lambda: client.get(f"/api/runs/{after['id']}").json()["status"] == "completed", 60
        )


def test_runs_take_a_name_and_tags_and_are_deleted(url: str) -> None:
    with httpx.Client(base_url=url, timeout=60) as client:
        made = client.post("/api/runs", json={**LONG, "name": "try one", "tags": ["a:b", "x=1"]})
        assert made.status_code == 201, made.text
        run = made.json()
        assert (run["name"], run["tags"], run["study_id"], run["condition"]) == (
            "try one",
            ["a:b", "x=1"],
            None,
            None,
        )
        assert "name" not in run["config"] and "tags" not in run["config"]
        plain = client.post("/api/runs", json=TINY).json()
        assert (plain["name"], plain["tags"]) == (None, [])
        for bad in ({"tags": ["no spaces"]}, {"tags": ["t"] * 17}, {"name": "n" * 129}):
            refused = client.post("/api/runs", json={**TINY, **bad})
            assert refused.status_code == 422, bad
        assert client.delete(f"/api/runs/{run['id']}").status_code == 204  # live: cancelled first
        assert client.get(f"/api/runs/{run['id']}").status_code == 404
        assert client.delete(f"/api/runs/{run['id']}").status_code == 404
        assert run["id"] not in [r["id"] for r in client.get("/api/runs").json()]
        assert eventually(
            lambda: client.get(f"/api/runs/{plain['id']}").json()["status"] == "completed", 60
        )
        best = client.get(f"/api/runs/{plain['id']}/best").json()["sha256"]
        assert client.delete(f"/api/runs/{plain['id']}").status_code == 204
        assert client.get(f"/api/controllers/{best}").status_code == 200  # controllers stay


def broken(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    raise RuntimeError("simulated evaluator crash")


def test_a_study_whose_runs_fail_ends_failed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every evaluation fails, on a zenoh worker and in the server (its physics broken by
    hand): the runs fail, and the study with them."""
    monkeypatch.setattr("server.runs.scheduler.evaluate", broken)
    zport = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        workers=0,
        executors=0,
    )
    with (
        serving(settings) as (base, _),
        httpx.Client(base_url=base, timeout=60) as client,
        worker_thread(zport, "crashy", broken),
    ):
        study = client.post(
            "/api/studies", json={"name": "crashing", "base": TINY, "seeds": [1, 2]}
        ).json()
        assert eventually(lambda: study_status(client, study["id"], "failed"), 60)
        failed = client.get(f"/api/studies/{study['id']}").json()
    assert {r["status"] for r in failed["runs"]} == {"failed"}
    assert failed["finished_at"] is not None
    assert [s["completed"] for s in failed["summary"]] == [0]
    assert failed["comparisons"] == [] and failed["verdicts"] == []
