"""`colony study ...`: start a study (many runs over conditions and seeds), follow it, show its
statistics and verdicts, export its data and figures.

A thin REST client (docs/studies.md): the server schedules the study's runs and computes the
statistics. A study is validated here with the server's own model before it is sent, so bad
input (an unreadable file, a malformed flag, an invalid study, a 422 from the server's limits)
prints one line and exits 2; other failures exit 1.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import typer
from rich.console import Console
from rich.table import Table

from colony.client import (
    DEFAULT_SERVER,
    JsonOpt,
    ServerOpt,
    TokenOpt,
    fetching,
    request,
    rich_console,
)
from colony.export import METRIC_ORDER, export_study
from colony.run_cli import FINAL, stopped_following

if TYPE_CHECKING:
    from pydantic import ValidationError

STUDY_POLL_S = 0.5
"""A study's view carries every run and its statistics: poll it gently."""
EXPLORATION = ("max_offset", "coverage")
"""Final metrics the server computes in the background after a run completes."""
EXPLORE_STALL_S = 60.0
"""--follow stops waiting for exploration figures when none has arrived for this long."""

study_app = typer.Typer(
    help="Studies: many runs over conditions and seeds, compared with statistics.",
    no_args_is_help=True,
)


def _bad_input(message: str) -> NoReturn:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


def _request(
    ctx: typer.Context, server: str, token: str | None, method: str, path: str, body: Any = None
) -> Any:
    """One request's JSON; a 422 exits 2 (bad input), any other failure 1."""
    return request(ctx, server, token, method, path, body, invalid_exit=2).json()


def load_mapping(path: Path) -> dict[str, Any]:
    """A JSON (.json) or YAML (any other suffix) file holding one object."""
    import yaml

    try:
        text = path.read_text()
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (OSError, ValueError, yaml.YAMLError) as exc:
        _bad_input(f"cannot read {path}: {' '.join(str(exc).split())}")
    if not isinstance(data, dict):
        _bad_input(f"{path} must hold an object (a mapping)")
    return data


def _value(text: str) -> Any:
    """A flag's value: JSON if it parses (numbers, true, null, objects), else the string."""
    try:
        return json.loads(text)
    except ValueError:
        return text


def _assignment(flag: str, text: str) -> tuple[str, str]:
    field, sep, value = text.partition("=")
    if not sep or not field.strip():
        _bad_input(f"{flag} {text!r}: expected FIELD=VALUE")
    return field.strip(), value


def _set(base: dict[str, Any], field: str, value: Any) -> None:
    """base[a][b] = value for a dotted field a.b (nested objects made as needed)."""
    *parents, leaf = field.split(".")
    node = base
    for part in parents:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            _bad_input(f"--set {field}: {part} is not an object")
        node = child
    node[leaf] = value


def _seeds(count: int | None, seed_list: str | None) -> list[int] | None:
    if count is not None and seed_list is not None:
        _bad_input("give --seeds or --seed-list, not both")
    if count is not None:
        if count < 1:
            _bad_input("--seeds must be at least 1")
        return list(range(count))
    if seed_list is None:
        return None
    try:
        return [int(s) for s in seed_list.split(",")]
    except ValueError:
        _bad_input(f"--seed-list {seed_list!r}: expected integers separated by commas")


def build_study(
    file: Path | None,
    *,
    name: str | None,
    seeds: list[int] | None,
    vary: list[str],
    overrides: list[str],
    base_file: Path | None,
) -> dict[str, Any]:
    """The StudyCreate body: FILE's, then the flags over it (--base replaces its base, --set
    fields go into the base, --vary adds grid fields)."""
    from pydantic import ValidationError

    from schemas.study import StudyCreate

    body = load_mapping(file) if file is not None else {}
    if name is not None:
        body["name"] = name
    if seeds is not None:
        body["seeds"] = seeds
    if base_file is not None:
        body["base"] = load_mapping(base_file)
        body["base"].pop("seed", None)  # a run's config.json has one; the study's seeds rule
    base = body.setdefault("base", {})
    if not isinstance(base, dict):
        _bad_input("base must be an object (a run config)")
    for text in overrides:
        field, value = _assignment("--set", text)
        _set(base, field, _value(value))
    if vary:
        grid = body.setdefault("grid", {})
        if not isinstance(grid, dict):
            _bad_input("grid must be an object")
        for text in vary:
            field, values = _assignment("--vary", text)
            grid[field] = [_value(v) for v in values.split(",")]
    for required in ("name", "seeds"):
        if required not in body:
            _bad_input(f"the study needs {required} (--{required} or a study file)")
    try:
        StudyCreate.model_validate(body)
    except ValidationError as exc:
        _bad_input(_validation_message(exc))
    return body


def _validation_message(exc: ValidationError) -> str:
    """'field: reason; ...', every offending field on one line."""
    parts = []
    for error in exc.errors():
        where = ".".join(str(p) for p in error["loc"])
        message = str(error["msg"]).removeprefix("Value error, ")
        parts.append(f"{where}: {message}" if where else message)
    return "; ".join(parts)


# --------------------------------------------------------------------------------- rendering


def _done(study: dict[str, Any]) -> int:
    return sum(r["status"] in FINAL for r in study["runs"])


def _figure(summary: dict[str, Any] | None) -> str:
    """'median [ci_low, ci_high]' of a Summary dict."""
    if not summary:
        return "-"
    return f"{summary['median']:.4g} [{summary['ci_low']:.4g}, {summary['ci_high']:.4g}]"


def study_table(study: dict[str, Any]) -> Table:
    """Per condition: runs done/total and each final metric's median [95 % CI]."""
    present = {m for s in study["summary"] for m in s["final"]}
    metrics = [m for m in METRIC_ORDER if m in present]
    metrics += sorted(present - set(metrics))
    table = Table(title=f"study {study['id']} {study['name']}: {study['status']}")
    for column in ("condition", "runs", *metrics):
        table.add_column(column)
    for s in study["summary"]:
        done = sum(r["status"] in FINAL for r in study["runs"] if r["condition"] == s["condition"])
        table.add_row(
            s["condition"], f"{done}/{s['runs']}", *(_figure(s["final"].get(m)) for m in metrics)
        )
    return table


def _print_study(study: dict[str, Any]) -> None:
    console = rich_console()
    console.print(study_table(study))
    for line in study["verdicts"]:
        console.print(line, highlight=False)


def _unexplored(study: dict[str, Any]) -> int:
    """Completed runs whose champion's exploration figures the server has not computed yet."""
    return sum(
        r["status"] == "completed" and any(r["metrics"].get(m) is None for m in EXPLORATION)
        for r in study["runs"]
    )


def follow_study(
    ctx: typer.Context, server: str, token: str | None, study_id: int, console: Console
) -> dict[str, Any]:
    """A progress bar of finished runs until the study is no longer running, then of the
    champions' exploration reports (the server computes them after the runs) until they are
    known or none arrives for EXPLORE_STALL_S; its StudyOut."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    tick = threading.Event()
    stalled_at: float | None = None
    pending = -1
    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
    ) as bar:
        task = bar.add_task(f"study {study_id}", total=None)
        while True:
            study: dict[str, Any] = _request(ctx, server, token, "GET", f"/api/studies/{study_id}")
            if study["status"] == "running":
                bar.update(task, total=len(study["runs"]), completed=_done(study))
            else:
                left = _unexplored(study)
                completed = sum(r["status"] == "completed" for r in study["runs"])
                bar.update(
                    task,
                    description=f"study {study_id} exploration",
                    total=completed,
                    completed=completed - left,
                )
                now = time.monotonic()
                if left != pending:
                    pending, stalled_at = left, now
                if left == 0 or (stalled_at is not None and now - stalled_at > EXPLORE_STALL_S):
                    return study
            tick.wait(STUDY_POLL_S)


def _finish(
    ctx: typer.Context,
    server: str,
    token: str | None,
    study: dict[str, Any],
    follow: bool,
    as_json: bool,
) -> None:
    if follow:
        try:
            study = follow_study(ctx, server, token, study["id"], rich_console(stderr=True))
        except KeyboardInterrupt:
            sid = study["id"]
            stopped_following(f"study {sid}", f"colony study show {sid} --follow", server)
    if as_json:
        typer.echo(json.dumps(study, indent=2))
    else:
        _print_study(study)
    if follow:
        for r in study["runs"]:
            if r["status"] == "failed":
                run = _request(ctx, server, token, "GET", f"/api/runs/{r['run_id']}")
                reason = run["error"] or "no reason recorded"
                typer.echo(f"run {r['run_id']} ({r['name']}) failed: {reason}", err=True)
    if follow and study["status"] != "completed":
        raise typer.Exit(1)


# ---------------------------------------------------------------------------------- commands


@study_app.command("start")
def study_start(
    ctx: typer.Context,
    file: Annotated[
        Path | None, typer.Argument(help="a study (StudyCreate) as JSON or YAML; flags override")
    ] = None,
    name: Annotated[str | None, typer.Option("--name", help="the study's name")] = None,
    seeds: Annotated[
        int | None, typer.Option("--seeds", help="N seeds: 0..N-1", show_default=False)
    ] = None,
    seed_list: Annotated[str | None, typer.Option("--seed-list", help="seeds, e.g. 1,2,3")] = None,
    vary: Annotated[
        list[str] | None,
        typer.Option(
            "--vary", help="FIELD=V1,V2: a grid field (repeatable; conditions are the product)"
        ),
    ] = None,
    overrides: Annotated[
        list[str] | None,
        typer.Option("--set", help="FIELD=VALUE in the base config, a.b for nested (repeatable)"),
    ] = None,
    base_file: Annotated[
        Path | None, typer.Option("--base", help="the base run config, JSON or YAML")
    ] = None,
    follow: Annotated[
        bool, typer.Option("--follow", help="a progress bar until the study ends")
    ] = False,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Start a study; without conditions or --vary it has one condition, "base".

    With --follow, exit status 1 unless every run completes."""
    body = build_study(
        file,
        name=name,
        seeds=_seeds(seeds, seed_list),
        vary=vary or [],
        overrides=overrides or [],
        base_file=base_file,
    )
    study = _request(ctx, server, token, "POST", "/api/studies", body)
    _finish(ctx, server, token, study, follow, as_json)


@study_app.command("show")
def study_show(
    ctx: typer.Context,
    study_id: int,
    follow: Annotated[
        bool, typer.Option("--follow", help="a progress bar until the study ends")
    ] = False,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Per condition: runs done and each final metric's median [95 % CI]; then the verdicts."""
    study = _request(ctx, server, token, "GET", f"/api/studies/{study_id}")
    _finish(ctx, server, token, study, follow, as_json)


@study_app.command("list")
def study_list(
    ctx: typer.Context,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Every study, newest first."""
    studies = _request(ctx, server, token, "GET", "/api/studies")
    if as_json:
        typer.echo(json.dumps(studies, indent=2))
        return
    table = Table(title="studies")
    for column in ("id", "name", "status", "conditions", "seeds", "runs", "created"):
        table.add_column(column)
    for s in studies:
        table.add_row(
            str(s["id"]),
            s["name"],
            s["status"],
            ", ".join(c["condition"] for c in s["summary"]),
            str(len(s["seeds"])),
            f"{_done(s)}/{len(s['runs'])}",
            str(s["created_at"]),
        )
    rich_console().print(table)


@study_app.command("export")
def study_export(
    ctx: typer.Context,
    study_id: int,
    out: Annotated[Path, typer.Option("--out", help="directory for the files (created)")],
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
) -> None:
    """CSV and Parquet tables (generations, individuals, champions, summary, comparisons) and
    the figures fitness.png and metrics.png."""
    study = _request(ctx, server, token, "GET", f"/api/studies/{study_id}")
    try:
        with fetching(ctx, server, token) as fetch:
            written = export_study(study, fetch, out)
    except OSError as exc:
        typer.echo(f"error: cannot write {out}: {exc}", err=True)
        raise typer.Exit(1) from exc
    for path in written:
        typer.echo(str(path))


@study_app.command("cancel")
def study_cancel(
    ctx: typer.Context, study_id: int, server: ServerOpt = DEFAULT_SERVER, token: TokenOpt = None
) -> None:
    """Cancel the study's unfinished runs; its completed runs and their statistics stay."""
    study = _request(ctx, server, token, "POST", f"/api/studies/{study_id}/cancel")
    typer.echo(f"study {study['id']} {study['status']}")


@study_app.command("delete")
def study_delete(
    ctx: typer.Context, study_id: int, server: ServerOpt = DEFAULT_SERVER, token: TokenOpt = None
) -> None:
    """Delete the study and every run of it, with their generations (not undoable)."""
    request(ctx, server, token, "DELETE", f"/api/studies/{study_id}", invalid_exit=2)
    typer.echo(f"study {study_id} deleted")
