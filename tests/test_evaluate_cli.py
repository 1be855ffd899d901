"""`colony evaluate` and GET /api/controllers/{sha256}/evaluation and /robustness: the
exploration report and the robustness map of a file or a stored controller, in the document's
world, with every bad input refused by name."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from typer.testing import CliRunner

from colony.cli import app
from evorobotics.document import ControllerDocument
from evorobotics.explore import MAX_ROBOT_STEPS, explore
from evorobotics.robustness import robustness
from schemas.network import PRESETS
from schemas.run import ValidationScore
from schemas.world import World
from server.runs import crud
from tests.helpers import Served, completed_run, serve

REACTIVE = PRESETS["reactive"]
SMALL = ["--poses", "30", "--steps", "150"]


def document(
    seed: int, validation: ValidationScore | None = None, world: World | None = None
) -> ControllerDocument:
    weights = np.random.default_rng(seed).uniform(-1.0, 1.0, REACTIVE.weight_count)
    return ControllerDocument(REACTIVE, weights, 4.5, {"run": "test"}, validation, world)


CHAMPION = document(
    1,
    validation=ValidationScore(
        poses=10,
        steps=50,
        seed=3,
        candidates=5,
        training_rank=2,
        score=7.25,
        stuck=0.1,
        roaming=0.6,
    ),
    world=World(max_speed=0.2, stuck_after=3),
)
PLAIN = document(2)


def invoke(*args: str) -> tuple[int, str, str]:
    done = CliRunner().invoke(app, ["evaluate", *args])
    return done.exit_code, done.stdout, done.stderr


def test_json_is_explore_in_the_documents_world(tmp_path: Path) -> None:
    path = tmp_path / "best.json"
    path.write_text(CHAMPION.to_json())
    code, out, err = invoke(str(path), *SMALL, "--seed", "2", "--json")
    assert code == 0, err
    got = json.loads(out)
    want = explore(REACTIVE, CHAMPION.weights, poses=30, steps=150, seed=2, world=CHAMPION.world)
    assert got["controller"] == CHAMPION.sha256 and got["world"] == "document"
    assert got["stuck_fraction_by_step"] == {str(h): v for h, v in want.stuck.items()}
    assert list(got["stuck_fraction_by_step"]) == ["40", "150"]
    assert got["mean_max_offset_m_by_step"] == {str(h): v for h, v in want.max_offset.items()}
    assert (got["confined_fraction"], got["roaming_fraction"]) == (want.confined, want.roaming)
    assert got["mean_coverage_cells"] == want.coverage
    assert got["mean_fitness_40_steps"] == want.fitness_40
    assert got["training_fitness"] == 4.5
    assert CHAMPION.validation is not None
    assert got["validation"] == CHAMPION.validation.model_dump(mode="json")
    default_world = explore(REACTIVE, CHAMPION.weights, poses=30, steps=150, seed=2)
    assert default_world != want  # the world really is the document's
    for threads in ("1", "3"):  # the same report on any number of threads
        code, again, err = invoke(str(path), *SMALL, "--seed", "2", "--json", "--threads", threads)
        assert code == 0 and again == out, err


def test_table_labels_the_measures_and_the_documents_own_scores(tmp_path: Path) -> None:
    champion, plain = tmp_path / "champion.json", tmp_path / "plain.json"
    champion.write_text(CHAMPION.to_json())
    plain.write_text(PLAIN.to_json())
    code, out, err = invoke(str(champion), *SMALL, "--reality-gap")
    assert code == 0, err
    for label in ("stuck by step 40", "stuck by step 150", "confined", "roaming", "coverage"):
        assert label in out
    assert "the document's world" in out and "reality gap" in out
    assert "training fitness" in out and "4.500" in out
    assert "validation (10 poses x 50 steps" in out and "score 7.250" in out
    code, out, err = invoke(str(plain), *SMALL, "--maze", "gen:3:1")
    assert code == 0, err
    assert "the default World" in out and "validation: none" in out and "'gen:3:1'" in out


def test_bad_input_is_one_line_and_exit_2(tmp_path: Path) -> None:
    good = tmp_path / "good.json"
    good.write_text(PLAIN.to_json())
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    tampered = tmp_path / "tampered.json"
    body = PLAIN.to_dict()
    body["sha256"] = "0" * 64
    tampered.write_text(json.dumps(body))
    cases = [
        ([str(tmp_path / "missing.json")], "missing.json"),
        ([str(bad_json)], "invalid JSON"),
        ([str(tampered)], "sha256 mismatch"),
        ([str(good), "--poses", str(MAX_ROBOT_STEPS), "--steps", "2"], "exceeds"),
        ([str(good), "--poses", "0"], "--poses"),
        ([str(good), "--threads", "0"], "--threads"),
        ([str(good), "--maze", "no-such-maze"], "--maze"),
        ([str(good), "--server", "http://127.0.0.1:9"], "not both"),
        (["--server", "http://127.0.0.1:9"], "exactly one of --run, --sha"),
    ]
    for args, reason in cases:
        code, out, err = invoke(*args)
        assert code == 2, (args, out, err)
        assert err.startswith("colony evaluate: ") and reason in err, (args, err)
        assert err.count("\n") == 1 and out == ""


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """A real server on an SQLite file with CHAMPION and PLAIN stored."""
    with serve(tmp_path_factory.mktemp("evaluate")) as served:
        with served.app.state.manager.sessions.begin() as session:
            for doc in (CHAMPION, PLAIN):
                crud.put_controller(
                    session,
                    sha256=doc.sha256,
                    document=doc.to_json(),
                    run_id=None,
                    generation=None,
                    fitness=doc.fitness,
                )
        yield served


def test_rest_evaluation_is_explore_plus_the_sha(served: Served) -> None:
    params: dict[str, str | int] = {
        "poses": 25,
        "steps": 120,
        "seed": 4,
        "maze": "arena",
        "reality_gap": "true",
    }
    url = f"{served.url}/api/controllers/{CHAMPION.sha256}/evaluation"
    first = httpx.get(url, params=params, timeout=30)
    assert first.status_code == 200, first.text
    want = explore(
        REACTIVE,
        CHAMPION.weights,
        poses=25,
        steps=120,
        seed=4,
        maze="arena",
        reality_gap=True,
        world=CHAMPION.world,
    )
    assert first.json() == {**want.as_dict(), "sha256": CHAMPION.sha256}
    again = httpx.get(url, params=params, timeout=30)  # the cached answer is the same answer
    assert again.content == first.content
    other = httpx.get(url, params={**params, "seed": 5}, timeout=30).json()
    assert other["seed"] == 5 and other != first.json()


def test_rest_evaluation_refuses_bad_parameters_by_name(served: Served) -> None:
    url = f"{served.url}/api/controllers/{PLAIN.sha256}/evaluation"
    refused: list[tuple[dict[str, str | int], str]] = [
        ({"poses": 0}, "poses"),
        ({"poses": 1001}, "poses"),
        ({"steps": 2001}, "steps"),
        ({"seed": -1}, "seed"),
        ({"poses": 1000, "steps": 1001}, "poses x steps"),
        ({"maze": "/etc/passwd"}, "maze"),
        ({"maze": "gen:1000:1"}, "maze"),
        ({"maze": "gen:x"}, "maze"),
        ({"maze": "x" * 5000}, "maze"),
    ]
    for params, name in refused:
        answer = httpx.get(url, params=params, timeout=30)
        assert answer.status_code == 422, (params, answer.text)
        assert name in answer.json()["detail"], (params, answer.text)
    unknown = httpx.get(f"{served.url}/api/controllers/{'0' * 64}/evaluation", timeout=30)
    assert unknown.status_code == 404 and "0" * 64 in unknown.json()["detail"]


def test_cli_evaluates_a_stored_controller(served: Served) -> None:
    code, out, err = invoke("--server", served.url, "--sha", PLAIN.sha256, *SMALL, "--json")
    assert code == 0, err
    got = json.loads(out)
    want = explore(REACTIVE, PLAIN.weights, poses=30, steps=150)
    assert got["controller"] == PLAIN.sha256 and got["world"] == "default"
    assert got["roaming_fraction"] == want.roaming and got["mean_coverage_cells"] == want.coverage
    code, out, err = invoke("--server", served.url, "--run", "99", *SMALL)
    assert code == 2 and "404" in err and err.startswith("colony evaluate: ")


def test_cli_evaluates_a_runs_best(served: Served) -> None:
    run_id = completed_run(
        served.url,
        {"population": 12, "generations": 2, "steps": 20, "validation": {"poses": 5, "steps": 40}},
    )
    best = ControllerDocument.from_json(
        httpx.get(f"{served.url}/api/runs/{run_id}/best", timeout=30).content
    )
    code, out, err = invoke("--server", served.url, "--run", str(run_id), *SMALL, "--json")
    assert code == 0, err
    got = json.loads(out)
    want = explore(best.spec, best.weights, poses=30, steps=150, world=best.world)
    assert got["controller"] == best.sha256 and got["roaming_fraction"] == want.roaming
    assert got["training_fitness"] == best.fitness


def test_robustness_map_from_the_cli_prints_tables_json_and_a_heat_map(tmp_path: Path) -> None:
    path = tmp_path / "best.json"
    path.write_text(CHAMPION.to_json())
    small = ["--robustness", "--poses", "4", "--steps", "60", "--seed", "2"]
    code, out, err = invoke(str(path), *small, "--json", "--out", str(tmp_path / "a"))
    assert code == 0, err
    want = robustness(REACTIVE, CHAMPION.weights, poses=4, steps=60, seed=2, world=CHAMPION.world)
    assert json.loads(out) == {"controller": CHAMPION.sha256, **want.as_dict()}
    assert (tmp_path / "a" / "robustness.png").read_bytes().startswith(b"\x89PNG")
    code, out, err = invoke(str(path), *small, "--out", str(tmp_path / "b"))
    assert code == 0, err
    assert "roaming, % of trials" in out and "stuck, % of trials" in out and "25 mm" in out
    assert f"{100 * want.roaming[0][0]:.0f}" in out and "robustness.png" in out
    code, _, err = invoke(str(path), *small, "--reality-gap")
    assert code == 2 and "--reality-gap" in err and err.startswith("colony evaluate: ")
    code, _, err = invoke(str(path), "--robustness", "--poses", "10000", "--steps", "1000")
    assert code == 2 and "exceeds the limit" in err


def test_rest_robustness_is_the_map_plus_the_sha_and_refuses_bad_parameters(
    served: Served,
) -> None:
    url = f"{served.url}/api/controllers/{CHAMPION.sha256[:12]}/robustness"
    params: dict[str, str | int] = {"poses": 3, "steps": 50, "seed": 1, "maze": "arena"}
    first = httpx.get(url, params=params, timeout=60)
    assert first.status_code == 200, first.text
    want = robustness(
        REACTIVE, CHAMPION.weights, poses=3, steps=50, seed=1, maze="arena", world=CHAMPION.world
    )
    assert first.json() == {**want.as_dict(), "sha256": CHAMPION.sha256}
    assert httpx.get(url, params=params, timeout=60).content == first.content
    refused: list[tuple[dict[str, str | int], str]] = [
        ({"poses": 0}, "poses"),
        ({"poses": 201}, "poses"),
        ({"steps": 2001}, "steps"),
        ({"seed": -1}, "seed"),
        ({"poses": 200, "steps": 501}, "poses x steps"),
        ({"maze": "/etc/passwd"}, "maze"),
        ({"maze": "gen:1000:1"}, "maze"),
    ]
    for bad, name in refused:
        answer = httpx.get(url, params=bad, timeout=30)
        assert answer.status_code == 422, (bad, answer.text)
        assert name in answer.json()["detail"], (bad, answer.text)
    unknown = httpx.get(f"{served.url}/api/controllers/{'0' * 64}/robustness", timeout=30)
    assert unknown.status_code == 404
