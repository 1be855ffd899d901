"""`colony study ...` and `colony run export|best|list` against a real server under uvicorn: a
small study from flags followed to the end, its table and verdicts, its export (every file,
Parquet equal to CSV, valid PNGs), study files in YAML and JSON, bad input refused in one line."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pyarrow.parquet as pq
import pytest
import yaml
from PIL import Image
from typer.testing import CliRunner

from colony.cli import app
from colony.export import (
    CHAMPION_COLUMNS,
    COMPARISON_COLUMNS,
    GENERATION_COLUMNS,
    INDIVIDUAL_COLUMNS,
    SUMMARY_COLUMNS,
    Kind,
    read_csv_table,
)
from server.core.settings import Settings
from tests.helpers import free_port, serving

TINY: dict[str, Any] = {
    "population": 8,
    "generations": 2,
    "trials": 1,
    "steps": 20,
    "validation": {"poses": 2, "steps": 50, "candidates": 4},
}
CONDITIONS = ["network=paper-best", "network=reactive"]
TABLES: dict[str, tuple[tuple[str, Kind], ...]] = {
    "generations": GENERATION_COLUMNS,
    "individuals": INDIVIDUAL_COLUMNS,
    "champions": CHAMPION_COLUMNS,
    "summary": SUMMARY_COLUMNS,
    "comparisons": COMPARISON_COLUMNS,
}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A server evaluating in two in-process threads (no zenoh workers); a run may hold
    100,000 weights."""
    tmp = tmp_path_factory.mktemp("study-cli")
    settings = Settings(
        db_url=f"sqlite:///{tmp / 's.db'}",
        port=free_port(),
        workers=0,
        zenoh=False,
        executors=2,
        max_population_weights=100_000,
    )
    with serving(settings) as (url, _):
        yield url


def colony(*args: str) -> tuple[int, str, str]:
    """Exit code, stdout and stderr of one CLI call."""
    result = CliRunner().invoke(app, list(args), env={"COLUMNS": "250"})
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture(scope="module")
def study(server: str) -> dict[str, Any]:
    """2 conditions x 2 seeds of tiny runs, started with flags and followed to the end."""
    sets = [f"--set={k}={json.dumps(v)}" for k, v in TINY.items()]
    code, out, err = colony(
        "study", "start", "--name", "cli", "--seeds", "2",
        "--vary", "network=paper-best,reactive", *sets, "--follow", "--json", "--server", server,
    )  # fmt: skip
    assert code == 0, err
    return dict(json.loads(out))


def test_flags_make_a_grid_over_seeds_that_completes(study: dict[str, Any]) -> None:
    assert study["status"] == "completed"
    assert [s["condition"] for s in study["summary"]] == CONDITIONS
    assert sorted((r["condition"], r["seed"]) for r in study["runs"]) == [
        (c, s) for c in CONDITIONS for s in (0, 1)
    ]
    assert study["base"]["population"] == 8 and study["base"]["validation"]["poses"] == 2


def test_show_and_list_print_the_conditions_and_verdicts(
    server: str, study: dict[str, Any]
) -> None:
    code, out, err = colony("study", "show", str(study["id"]), "--server", server)
    assert code == 0, err
    for condition in CONDITIONS:
        line = next(x for x in out.splitlines() if condition in x)
        assert "2/2" in line and "[" in line  # runs done/total, a median [CI]
    for verdict in study["verdicts"]:
        assert verdict in out
    code, out, err = colony("study", "list", "--server", server)
    assert code == 0, err
    assert "cli" in out and "completed" in out and "4/4" in out
    code, out, _ = colony("study", "show", str(study["id"]), "--json", "--server", server)
    assert json.loads(out)["id"] == study["id"]


def test_export_writes_every_file_parquet_equal_to_csv(
    server: str, study: dict[str, Any], tmp_path: Path
) -> None:
    out = tmp_path / "export"
    code, stdout, err = colony("study", "export", str(study["id"]), "--out", str(out), "--server", server)  # fmt: skip
    assert code == 0, err
    expected = {f"{t}.{x}" for t in TABLES for x in ("csv", "parquet")} | {
        "fitness.png",
        "metrics.png",
    }
    assert {p.name for p in out.iterdir()} == expected
    assert sorted(Path(line).name for line in stdout.split()) == sorted(expected)
    tables = {}
    for name, columns in TABLES.items():
        parquet = pq.read_table(out / f"{name}.parquet")
        assert parquet.column_names == [c for c, _ in columns]
        rows = read_csv_table(out / f"{name}.csv", columns)
        assert rows == parquet.to_pylist(), name
        tables[name] = rows
    assert len(tables["generations"]) == 4 * TINY["generations"]
    assert len(tables["individuals"]) == 4 * TINY["population"]
    assert {r["study"] for r in tables["generations"]} == {"cli"}
    assert sorted((r["condition"], r["seed"]) for r in tables["champions"]) == [
        (c, s) for c in CONDITIONS for s in (0, 1)
    ]
    for champion in tables["champions"]:  # --follow waited for the exploration figures too
        assert None not in (champion["max_offset"], champion["coverage"]), champion
    assert {r["condition"] for r in tables["summary"]} == set(CONDITIONS)
    assert len(tables["comparisons"]) == len(study["comparisons"])
    for png in ("fitness.png", "metrics.png"):
        with Image.open(out / png) as image:
            image.verify()
            assert image.format == "PNG" and image.size[0] > 300


def test_run_commands_export_best_and_list(
    server: str, study: dict[str, Any], tmp_path: Path
) -> None:
    run = study["runs"][0]
    code, out, err = colony("run", "best", str(run["run_id"]), "--out", str(tmp_path / "b.json"), "--server", server)  # fmt: skip
    assert code == 0, err
    document = json.loads((tmp_path / "b.json").read_text())
    assert document["sha256"] in out and "validation" in document
    served = httpx.get(f"{server}/api/runs/{run['run_id']}/best").content
    assert (tmp_path / "b.json").read_bytes() == served

    code, out, err = colony("run", "export", str(run["run_id"]), "--out", str(tmp_path / "r"), "--server", server)  # fmt: skip
    assert code == 0, err
    generations = pq.read_table(tmp_path / "r" / "generations.parquet").to_pylist()
    assert generations == read_csv_table(tmp_path / "r" / "generations.csv", GENERATION_COLUMNS)
    assert [g["generation"] for g in generations] == [0, 1]
    assert {(g["study"], g["condition"], g["seed"]) for g in generations} == {
        ("cli", run["condition"], run["seed"])
    }
    individuals = pq.read_table(tmp_path / "r" / "individuals.parquet").to_pylist()
    assert [i["rank"] for i in individuals] == list(range(TINY["population"]))
    assert document["sha256"] in {i["sha256"] for i in individuals}

    code, out, err = colony("run", "list", "--server", server)
    assert code == 0, err
    line = next(x for x in out.splitlines() if run["name"] in x)
    for cell in ("paper", "paper-ga", run["condition"], "completed", "2/2"):
        assert cell in line, cell


@pytest.mark.parametrize("suffix", ["yaml", "json"])
def test_study_files_in_yaml_and_json(server: str, tmp_path: Path, suffix: str) -> None:
    body = {
        "name": f"file-{suffix}",
        "base": {**TINY, "generations": 1},
        "conditions": {"paper": {}, "eta-half": {"ga": {"eta": 0.5}}},
        "seeds": [7],
    }
    path = tmp_path / f"study.{suffix}"
    path.write_text(yaml.safe_dump(body, sort_keys=False) if suffix == "yaml" else json.dumps(body))
    code, out, err = colony("study", "start", str(path), "--json", "--server", server)
    assert code == 0, err
    created = json.loads(out)
    assert created["name"] == f"file-{suffix}" and created["seeds"] == [7]
    assert list(created["conditions"]) == ["paper", "eta-half"]
    httpx.delete(f"{server}/api/studies/{created['id']}").raise_for_status()


def _write(tmp: Path, name: str, text: str) -> str:
    (tmp / name).write_text(text)
    return str(tmp / name)


BAD: dict[str, list[str]] = {
    "no file": ["missing.yaml"],
    "bad yaml": ["@bad.yaml"],
    "not a mapping": ["@list.json"],
    "no seeds": ["--name", "x"],
    "seeds twice": ["--name", "x", "--seeds", "2", "--seed-list", "1,2"],
    "bad seed list": ["--name", "x", "--seed-list", "1,a"],
    "vary without =": ["--name", "x", "--seeds", "2", "--vary", "network"],
    "bad name": ["--name", "a b", "--seeds", "2"],
    "seed overridden": ["--name", "x", "--seeds", "2", "--vary", "seed=1,2"],
    "bad field": ["--name", "x", "--seeds", "2", "--set", "population=2"],
    "over the server's limit": ["--name", "x", "--seeds", "2", "--set", "population=5000"],
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_prints_one_line_and_exits_2(server: str, tmp_path: Path, case: str) -> None:
    files = {
        "@bad.yaml": _write(tmp_path, "bad.yaml", "name: [unclosed\n"),
        "@list.json": _write(tmp_path, "list.json", "[1, 2]"),
    }
    args = [files.get(a, a) for a in BAD[case]]
    code, out, err = colony("study", "start", *args, "--server", server)
    assert code == 2, (out, err)
    assert len(err.strip().splitlines()) == 1 and err.startswith("error"), err
    assert out == ""


def test_cancel_then_delete_a_study_and_delete_a_run(server: str) -> None:
    """`colony study cancel` ends what still runs, `colony study delete` removes the study and
    its runs, `colony run delete` one run; an unknown study is refused with the server's 404."""
    sets = [f"--set={k}={json.dumps(v)}" for k, v in {**TINY, "generations": 5000}.items()]
    code, out, err = colony(
        "study", "start", "--name", "long", "--seeds", "2", *sets, "--json", "--server", server
    )
    assert code == 0, err
    created = json.loads(out)
    code, out, err = colony("study", "cancel", str(created["id"]), "--server", server)
    assert code == 0, err
    assert out.strip() == f"study {created['id']} cancelled"
    runs = httpx.get(f"{server}/api/studies/{created['id']}").json()["runs"]
    assert {r["status"] for r in runs} == {"cancelled"}
    code, out, err = colony("run", "delete", str(runs[0]["run_id"]), "--server", server)
    assert code == 0 and out.strip() == f"run {runs[0]['run_id']} deleted", err
    assert httpx.get(f"{server}/api/runs/{runs[0]['run_id']}").status_code == 404
    code, out, err = colony("study", "delete", str(created["id"]), "--server", server)
    assert code == 0 and out.strip() == f"study {created['id']} deleted", err
    assert httpx.get(f"{server}/api/studies/{created['id']}").status_code == 404
    assert httpx.get(f"{server}/api/runs/{runs[1]['run_id']}").status_code == 404
    code, out, err = colony("study", "delete", str(created["id"]), "--server", server)
    assert code == 1 and err.strip() == f"error 404: no study with id {created['id']}", (out, err)


def test_run_start_takes_a_strategy_and_the_server_names_a_bad_one(server: str) -> None:
    sets = ["--population", "8", "--generations", "2", "--steps", "20", "--trials", "1"]
    code, out, err = colony(
        "run", "start", *sets, "--strategy", "cma-es", "--follow", "--json", "--server", server
    )
    assert code == 0, err
    run = json.loads(out)
    assert run["status"] == "completed" and run["config"]["strategy"] == "cma-es"
    code, out, err = colony("run", "start", "--strategy", "hill-climbing", "--server", server)
    assert code == 1 and len(err.strip().splitlines()) == 1 and "strategy" in err, err
