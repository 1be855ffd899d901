"""REST client commands against a real server: --follow, --json outputs parse, tables, errors."""

from __future__ import annotations

import json
import re
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import typer
import uvicorn
from typer.testing import CliRunner

from colony.cli import app
from server.app import create_app
from server.core.settings import Settings
from tests.helpers import eventually, free_port

SMALL = ["--population", "8", "--generations", "3", "--steps", "10", "--job-size", "4"]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A server with its robot service (zenoh on a free port), one in-process evaluator."""
    tmp = tmp_path_factory.mktemp("cli")
    port = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp / 'c.db'}",
        port=port,
        workers=0,
        executors=1,
        zenoh_listen=[f"tcp/127.0.0.1:{free_port()}"],
    )
    uv = uvicorn.Server(
        uvicorn.Config(create_app(settings), host="127.0.0.1", port=port, log_level="warning")
    )
    thread = threading.Thread(target=uv.run, daemon=True)
    thread.start()
    try:
        assert eventually(lambda: uv.started or not thread.is_alive())
        assert uv.started, "uvicorn did not start"
        yield f"http://127.0.0.1:{port}"
    finally:
        uv.should_exit = True
        thread.join(timeout=30)


def colony(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})
    return result.exit_code, result.output


def test_follow_then_every_read_command_json_parses(server: str) -> None:
    code, out = colony("run", "start", *SMALL, "--follow", "--json", "--server", server)
    assert code == 0, out
    run = json.loads(out[out.index("{") :])
    assert run["status"] == "completed" and run["generation"] == 3
    reads = {
        ("run", "list"): list,
        ("run", "show", str(run["id"])): dict,
        ("status",): dict,
        ("workers",): list,
        ("robots",): list,
    }
    for command, kind in reads.items():
        code, out = colony(*command, "--server", server, "--json")
        assert code == 0, (command, out)
        assert isinstance(json.loads(out), kind), command
    code, out = colony("run", "show", str(run["id"]), "--server", server, "--json")
    assert [g["generation"] for g in json.loads(out)["history"]] == [0, 1, 2]


def test_follow_labels_the_training_fitness_and_ends_on_the_champion(server: str) -> None:
    """The bar gives the best training fitness so far beside the last generation's best (which
    falls as well as rises); the end names the champion and its held-out test."""
    code, out = colony("run", "start", *SMALL, "--follow", "--server", server)
    assert code == 0, out
    run = json.loads(colony("run", "list", "--server", server, "--json")[1])[0]
    best = run["best_fitness_so_far"]
    assert best == max(g["best"] for g in generations(server, run["id"]))
    assert "3/3" in out
    assert f"training fitness: best so far {best:.3f}" in out
    assert f"last generation's best {run['best_fitness']:.3f}" in out
    champion = run["champion"]
    assert f"run {run['id']} completed\nchampion {champion['sha256'][:12]}: training fitness" in out
    gap = champion["test"]["gap"]["roaming"]["value"]
    assert f"held-out test on {champion['test']['poses']} unseen poses" in out
    assert f"under the reality gap: roaming {gap:.0%}" in out
    code, out = colony("status", "--server", server)
    assert code == 0, out
    for title in ("active runs", "workers", "robots"):
        assert title in out


def generations(server: str, run_id: int) -> list[dict[str, float]]:
    code, out = colony("run", "show", str(run_id), "--server", server, "--json")
    assert code == 0, out
    history: list[dict[str, float]] = json.loads(out)["history"]
    return history


def table_rows(out: str) -> list[list[str]]:
    """The cells of each body row of the rich tables in `out`."""
    return [[c.strip() for c in line.split("│")[1:-1]] for line in out.splitlines() if "│" in line]


def test_show_and_list_name_the_champion_with_its_held_out_test(server: str) -> None:
    """`run show` says which controller the run exports and how it did on the held-out test,
    with about ten generations (the first, the last, the best) unless asked for all; `run list`
    gives each run's champion and test figures as nominal / under the gap."""
    code, out = colony(
        "run", "start", "--population", "8", "--generations", "25", "--steps", "10",
        "--job-size", "4", "--follow", "--json", "--server", server,
    )  # fmt: skip
    assert code == 0, out
    run = json.loads(out[out.index("{") :])
    run_id, champion = run["id"], run["champion"]
    test = champion["test"]
    best = client_best(server, run_id)
    assert champion["sha256"] == best["sha256"] and test == best["test"]
    assert champion["training_fitness"] == best["fitness"]

    code, out = colony("run", "show", str(run_id), "--server", server)
    assert code == 0, out
    assert f"champion {champion['sha256'][:12]}: training fitness" in out
    assert f"rank {champion['validation']['training_rank']}" in out
    assert f"held-out test on {test['poses']} unseen poses x {test['steps']} steps" in out
    history = generations(server, run_id)
    listed = [int(r[0]) for r in table_rows(out) if len(r) == 4 and r[0].isdigit()]
    top = max(range(25), key=lambda g: history[g]["best"])
    assert listed[0] == 0 and listed[-1] == 24 and top in listed
    assert 10 <= len(listed) <= 11 and listed == sorted(listed)
    assert "--all-generations lists every one" in out
    code, out = colony("run", "show", str(run_id), "--all-generations", "--server", server)
    assert code == 0, out
    assert [int(r[0]) for r in table_rows(out) if len(r) == 4 and r[0].isdigit()] == list(range(25))

    code, out = colony("run", "list", "--server", server)
    assert code == 0, out
    assert "champion" in out and "roaming nominal / gap" in out
    row = next(r for r in table_rows(out) if r[0] == str(run_id))
    nominal, gap = test["nominal"], test["gap"]
    assert row[-3:] == [
        champion["sha256"][:12],
        f"{nominal['roaming']['value']:.0%} / {gap['roaming']['value']:.0%}",
        f"{nominal['stuck']['value']:.0%} / {gap['stuck']['value']:.0%}",
    ]
    assert row[-4] == f"{max(g['best'] for g in history):.4g}"  # best training fitness so far


def test_a_live_run_has_no_champion_yet(server: str) -> None:
    code, out = colony(
        "run", "start", "--population", "8", "--generations", "5000", "--steps", "10",
        "--server", server, "--json",
    )  # fmt: skip
    assert code == 0, out
    run_id = json.loads(out)["id"]
    try:
        code, out = colony("run", "show", str(run_id), "--server", server)
        assert code == 0, out
        assert "no champion yet" in out
    finally:
        colony("run", "cancel", str(run_id), "--server", server)
    code, out = colony("run", "show", str(run_id), "--server", server)
    assert "no champion: the run was cancelled" in out


def client_best(server: str, run_id: int) -> dict[str, object]:
    import httpx

    best: dict[str, object] = httpx.get(f"{server}/api/runs/{run_id}/best", timeout=30).json()
    return best


def test_push_to_an_unknown_robot_fails_with_the_server_message(
    server: str, tmp_path: Path
) -> None:
    code, out = colony("robot", "push", "nobody", "--run", "1", "--server", server)
    assert code == 1
    assert "404" in out and "nobody" in out
    code, out = colony("robot", "push", "nobody", "--server", server)
    assert code != 0  # neither --run nor --sha


# ---------------------------------------------------------------- docs/configuration.md

CONFIG_DOC = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"
BEGIN, END = (
    "<!-- settings table: generated by tests/test_cli.py -->",
    "<!-- end settings table -->",
)


def server_flags() -> dict[str, str]:
    """COLONY_* env var -> `colony server` flag, read from the flags' help texts."""
    command = typer.main.get_command(app)
    flags: dict[str, str] = {}
    group: typer.core.TyperGroup = command  # type: ignore[assignment]
    for param in group.commands["server"].params:
        match = re.search(r"\[(COLONY_[A-Z_]+)", getattr(param, "help", None) or "")
        if match and param.opts:
            flags[match.group(1)] = param.opts[0]
    return flags


def settings_table() -> str:
    """The Markdown table of every Settings field: flag, env var, default, meaning."""
    flags = server_flags()
    rows = [
        "| setting | flag | environment | default | meaning |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, field in Settings.model_fields.items():
        env = f"COLONY_{name.upper()}"
        default = field.default
        shown = "(secret)" if field.repr is False and default is not None else json.dumps(default)
        flag = f"`{flags[env]}`" if env in flags else "-"
        meaning = (field.description or "").replace("|", "\\|")
        rows.append(f"| `{name}` | {flag} | `{env}` | `{shown}` | {meaning} |")
    return "\n".join(rows)


def test_configuration_doc_lists_every_setting() -> None:
    text = CONFIG_DOC.read_text()
    table = text[text.index(BEGIN) + len(BEGIN) : text.index(END)].strip()
    missing = [n for n in Settings.model_fields if f"`COLONY_{n.upper()}`" not in table]
    assert not missing, f"docs/configuration.md lacks {missing}: run python tests/test_cli.py"
    assert table == settings_table(), "docs/configuration.md is stale: run python tests/test_cli.py"


def test_every_field_has_a_meaning() -> None:
    assert [n for n, f in Settings.model_fields.items() if not f.description] == []


if __name__ == "__main__":  # regenerate the table in docs/configuration.md
    doc = CONFIG_DOC.read_text()
    head, rest = doc.split(BEGIN, 1)
    CONFIG_DOC.write_text(f"{head}{BEGIN}\n{settings_table()}\n{END}{rest.split(END, 1)[1]}")


def test_json_logs_carry_context_ids(capsys: pytest.CaptureFixture[str]) -> None:
    import logging

    from server.core.logs import configure, context

    root = logging.getLogger()
    saved = (root.handlers[:], root.level)
    try:
        configure("INFO", "json")
        context(logging.getLogger("colony.test"), run=3, job="3/1/0").info("leased %s", "x")
        logging.getLogger("colony.test").debug("hidden below INFO")
    finally:
        root.handlers[:], _ = saved
        root.setLevel(saved[1])
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1
    entry = json.loads(lines[0])
    assert entry["message"] == "leased x" and entry["level"] == "INFO"
    assert (entry["run"], entry["job"], entry["logger"]) == (3, "3/1/0", "colony.test")
    with pytest.raises(ValueError):
        configure("INFO", "yaml")  # type: ignore[arg-type]
