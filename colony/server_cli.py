"""`colony server` (the central server) and its REST clients: `colony run ...`, `colony status`.

The clients speak only the documented REST API (docs/api.md) through httpx; tests inject a
transport with `app(args, obj={"transport": ...})`. Server errors print the server's message
and exit non-zero.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import httpx
import typer
from rich.console import Console
from rich.table import Table

DEFAULT_SERVER = "http://127.0.0.1:8000"
TIMEOUT_S = 30.0

ServerOpt = Annotated[str, typer.Option("--server", help="server base URL")]
JsonOpt = Annotated[bool, typer.Option("--json", help="print the server's JSON")]

run_app = typer.Typer(
    help="Start and steer evolutionary runs on a colony server.", no_args_is_help=True
)


def serve(
    db: Annotated[str | None, typer.Option("--db", help="SQLAlchemy URL [COLONY_DB_URL]")] = None,
    host: Annotated[str | None, typer.Option(help="bind address [COLONY_HOST]")] = None,
    port: Annotated[int | None, typer.Option(help="HTTP port [COLONY_PORT]")] = None,
    zenoh_listen: Annotated[
        list[str] | None,
        typer.Option(
            "--zenoh-listen",
            help="zenoh endpoint to listen on, repeatable (default tcp/0.0.0.0:7447) "
            "[COLONY_ZENOH_LISTEN, a JSON list]",
        ),
    ] = None,
    zenoh_connect: Annotated[
        list[str] | None,
        typer.Option(
            "--zenoh-connect",
            help="a lab zenohd to join, e.g. tcp/HOST:7447; repeatable [COLONY_ZENOH_CONNECT]",
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="local worker processes; 0 waits for remote ones (default: one per spare "
            "core) [COLONY_WORKERS]"
        ),
    ] = None,
    no_zenoh: Annotated[
        bool,
        typer.Option(
            "--no-zenoh", help="no zenoh at all: evaluate in-process threads (--executors)"
        ),
    ] = False,
    executors: Annotated[
        int | None,
        typer.Option(
            help="in-process evaluation threads (default: 0 with zenoh, 1 with --no-zenoh) "
            "[COLONY_EXECUTORS]"
        ),
    ] = None,
) -> None:
    """Run the colony server: REST API (OpenAPI at /docs), store, run manager, zenoh router
    for workers (docs/protocol.md) and N local workers."""
    import uvicorn

    from server.app import create_app
    from server.settings import Settings

    overrides = {
        "db_url": db,
        "host": host,
        "port": port,
        "zenoh_listen": zenoh_listen or None,
        "zenoh_connect": zenoh_connect or None,
        "workers": workers,
        "executors": executors,
        "zenoh": False if no_zenoh else None,
    }
    try:
        settings = Settings.model_validate({k: v for k, v in overrides.items() if v is not None})
        app = create_app(settings)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="info")


def _client(ctx: typer.Context, server: str) -> httpx.Client:
    obj = ctx.find_root().obj
    transport = obj.get("transport") if isinstance(obj, dict) else None
    return httpx.Client(base_url=server.rstrip("/"), transport=transport, timeout=TIMEOUT_S)


def _call(ctx: typer.Context, server: str, method: str, path: str, body: Any = None) -> Any:
    """One request; the server's error message and exit status 1 on failure."""
    try:
        with _client(ctx, server) as client:
            response = client.request(method, path, json=body)
    except httpx.HTTPError as exc:
        typer.echo(f"error: cannot reach {server}: {exc}", err=True)
        raise typer.Exit(1) from exc
    if response.is_error:
        try:
            detail = response.json().get("detail", response.text)
        except ValueError:
            detail = response.text
        typer.echo(f"error {response.status_code}: {detail}", err=True)
        raise typer.Exit(1)
    return response.json()


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _runs_table(runs: list[dict[str, Any]], title: str) -> Table:
    table = Table(title=title)
    for column in ("id", "status", "generation", "best", "evaluations", "started", "error"):
        table.add_column(column)
    for run in runs:
        table.add_row(
            str(run["id"]),
            run["status"],
            f"{run['generation']}/{run['generations']}",
            _fmt(run["best_fitness"]),
            str(run["evaluations"]),
            _fmt(run["started_at"]),
            _fmt(run["error"]),
        )
    return table


def _print_json(data: Any) -> None:
    typer.echo(json.dumps(data, indent=2))


@run_app.command("start")
def run_start(
    ctx: typer.Context,
    config_file: Annotated[
        Path | None, typer.Option("--config", help="RunConfig JSON; flags override it")
    ] = None,
    population: Annotated[int | None, typer.Option()] = None,
    generations: Annotated[int | None, typer.Option()] = None,
    trials: Annotated[int | None, typer.Option()] = None,
    steps: Annotated[int | None, typer.Option()] = None,
    seed: Annotated[int | None, typer.Option()] = None,
    maze: Annotated[str | None, typer.Option()] = None,
    network: Annotated[str | None, typer.Option(help="preset name")] = None,
    job_size: Annotated[int | None, typer.Option("--job-size")] = None,
    server: ServerOpt = DEFAULT_SERVER,
    as_json: JsonOpt = False,
) -> None:
    """Start a run; unset fields default to the paper's experiment (validated by the server)."""
    body: dict[str, Any] = {}
    if config_file is not None:
        try:
            body = json.loads(config_file.read_text())
        except (OSError, ValueError) as exc:
            typer.echo(f"error: cannot read {config_file}: {exc}", err=True)
            raise typer.Exit(1) from exc
        if not isinstance(body, dict):
            typer.echo(f"error: {config_file} must hold a JSON object", err=True)
            raise typer.Exit(1)
    flags = {
        "population": population,
        "generations": generations,
        "trials": trials,
        "steps": steps,
        "seed": seed,
        "maze": maze,
        "network": network,
        "job_size": job_size,
    }
    body.update({k: v for k, v in flags.items() if v is not None})
    run = _call(ctx, server, "POST", "/api/runs", body)
    if as_json:
        _print_json(run)
    else:
        typer.echo(f"run {run['id']} {run['status']}")


@run_app.command("list")
def run_list(
    ctx: typer.Context, server: ServerOpt = DEFAULT_SERVER, as_json: JsonOpt = False
) -> None:
    """Every run, newest first."""
    runs = _call(ctx, server, "GET", "/api/runs")
    if as_json:
        _print_json(runs)
    else:
        Console().print(_runs_table(runs, "runs"))


@run_app.command("show")
def run_show(
    ctx: typer.Context, run_id: int, server: ServerOpt = DEFAULT_SERVER, as_json: JsonOpt = False
) -> None:
    """One run with its fitness per generation."""
    run = _call(ctx, server, "GET", f"/api/runs/{run_id}")
    generations = _call(ctx, server, "GET", f"/api/runs/{run_id}/generations")
    if as_json:
        _print_json({**run, "history": generations})
        return
    console = Console()
    console.print(_runs_table([run], f"run {run_id}"))
    table = Table(title="generations")
    for column in ("generation", "best", "mean", "worst"):
        table.add_column(column)
    for g in generations:
        table.add_row(str(g["generation"]), _fmt(g["best"]), _fmt(g["mean"]), _fmt(g["worst"]))
    console.print(table)


def _steer(ctx: typer.Context, server: str, run_id: int, action: str) -> None:
    run = _call(ctx, server, "POST", f"/api/runs/{run_id}/{action}")
    typer.echo(f"run {run['id']} {run['status']}")


@run_app.command("pause")
def run_pause(ctx: typer.Context, run_id: int, server: ServerOpt = DEFAULT_SERVER) -> None:
    """Stop handing out the run's jobs (jobs in hand finish)."""
    _steer(ctx, server, run_id, "pause")


@run_app.command("resume")
def run_resume(ctx: typer.Context, run_id: int, server: ServerOpt = DEFAULT_SERVER) -> None:
    """Continue a paused run."""
    _steer(ctx, server, run_id, "resume")


@run_app.command("cancel")
def run_cancel(ctx: typer.Context, run_id: int, server: ServerOpt = DEFAULT_SERVER) -> None:
    """End a run for good; its committed generations stay."""
    _steer(ctx, server, run_id, "cancel")


def status(
    ctx: typer.Context, server: ServerOpt = DEFAULT_SERVER, as_json: JsonOpt = False
) -> None:
    """Colony summary: runs by status, active runs, jobs, workers, robots."""
    colony = _call(ctx, server, "GET", "/api/colony")
    if as_json:
        _print_json(colony)
        return
    console = Console()
    counts = ", ".join(f"{k} {v}" for k, v in sorted(colony["runs"].items())) or "none"
    jobs = colony["jobs"]
    console.print(f"runs: {counts}")
    console.print(f"jobs: pending {jobs['pending']}, leased {jobs['leased']}, done {jobs['done']}")
    console.print(_runs_table(colony["active"], "active runs"))
    console.print(f"workers: {len(colony['workers'])}, robots: {len(colony['robots'])}")


def register(app: typer.Typer) -> None:
    """Add `server`, `run` and `status` to the root CLI."""
    app.command(name="server")(serve)
    app.add_typer(run_app, name="run")
    app.command(name="status")(status)
