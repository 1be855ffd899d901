"""`colony run ...`: start, follow and steer runs on a colony server over its REST API."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, NoReturn

import httpx
import typer
from rich.console import Console
from rich.table import Table

from colony.champion import held_out_cells, run_champion_lines, training_progress
from colony.client import (
    DEFAULT_SERVER,
    JsonOpt,
    ServerOpt,
    TokenOpt,
    call_server,
    cell,
    fetching,
    open_client,
    print_json,
    request,
    rich_console,
)
from colony.options import NominalOpt

FOLLOW_POLL_S = 0.2
FINAL = ("completed", "failed", "cancelled")

run_app = typer.Typer(
    help="Start and steer evolutionary runs on a colony server.", no_args_is_help=True
)


def _network(config: dict[str, Any]) -> str:
    """A preset's name, or a spec's layer sizes."""
    network = config.get("network")
    if isinstance(network, dict):
        return f"spec {network.get('hidden', [])}"
    return str(network)


def _maze(config: dict[str, Any]) -> str:
    """A maze's name, or "custom" for maze text."""
    maze = str(config.get("maze"))
    return "custom" if "\n" in maze else maze


def _study(run: dict[str, Any]) -> str:
    """STUDY_ID/CONDITION of a study's run, "-" otherwise."""
    if run.get("study_id") is None:
        return "-"
    return f"{run['study_id']}/{run.get('condition') or '-'}"


def runs_table(runs: list[dict[str, Any]], title: str) -> Table:
    """One row a run: what it is, how far it got, its best training fitness so far, and its
    champion with the champion's held-out test (nominal world / under the reality gap)."""
    table = Table(title=title)
    for column in ("id", "name", "status", "network", "maze", "seed", "strategy", "study"):
        # on a narrow terminal the long texts fold; the status and numbers stay whole
        table.add_column(column, no_wrap=column in ("id", "status", "seed"), overflow="fold")
    for column in ("generation", "best training fitness", "champion"):
        table.add_column(column, no_wrap=column != "best training fitness", overflow="fold")
    for column in ("roaming nominal / gap", "stuck nominal / gap"):
        table.add_column(column, overflow="fold")
    for run in runs:
        config = run["config"]
        table.add_row(
            str(run["id"]),
            cell(run.get("name")),
            run["status"],
            _network(config),
            _maze(config),
            str(run["seed"]),
            str(config.get("strategy") or "paper-ga"),
            _study(run),
            f"{run['generation']}/{run['generations']}",
            cell(run.get("best_fitness_so_far")),
            *held_out_cells(run.get("champion")),
        )
    return table


def follow_run(
    client: httpx.Client,
    run_id: int,
    console: Console,
    alive: Callable[[], None] = lambda: None,
    poll_s: float = FOLLOW_POLL_S,
) -> dict[str, Any]:
    """A progress bar of committed generations with the best training fitness so far and the
    last generation's best, until the run ends (completed, failed or cancelled); returns the
    final RunOut. `alive` may raise to abort."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    tick = threading.Event()
    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
    ) as bar:
        task = bar.add_task(f"run {run_id}", total=None)
        while True:
            response = client.get(f"/api/runs/{run_id}")
            response.raise_for_status()
            run: dict[str, Any] = response.json()
            text = f"run {run_id} " + training_progress(
                run.get("best_fitness_so_far"), run["best_fitness"]
            )
            bar.update(
                task, total=run["generations"], completed=run["generation"], description=text
            )
            if run["status"] in FINAL:
                return run
            alive()
            tick.wait(poll_s)


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
    maze: Annotated[
        str | None,
        typer.Option(
            metavar="NAME_OR_FILE",
            help="shipped maze (colony mazes), gen:SIZE:SEED, or a maze file (its text is sent)",
        ),
    ] = None,
    network: Annotated[
        str | None,
        typer.Option(
            metavar="PRESET_OR_FILE",
            help="network preset (colony presets) or NetworkSpec JSON file (its spec is sent)",
        ),
    ] = None,
    nominal: NominalOpt = False,
    for_colony: Annotated[
        bool,
        typer.Option(
            "--for-colony",
            help="train for the colony you have: each trial's robot drawn from the server's "
            "calibrated robots (reality_gap colony) instead of the paper's gap",
        ),
    ] = False,
    job_size: Annotated[int | None, typer.Option("--job-size")] = None,
    strategy: Annotated[
        str | None,
        typer.Option(help="paper-ga, cma-es, sep-cma-es, map-elites, cma-me or novelty [paper-ga]"),
    ] = None,
    name: Annotated[
        str | None, typer.Option("--name", help="what `run list` and the dashboard call it")
    ] = None,
    tags: Annotated[
        list[str] | None,
        typer.Option("--tag", metavar="TAG", help="a label to find it by, repeatable"),
    ] = None,
    follow: Annotated[
        bool, typer.Option("--follow", help="show a progress bar until the run ends")
    ] = False,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Start a run; unset fields default to the paper's experiment (validated by the server).

    With --follow, exit status 1 unless the run completes."""
    from colony.run_inputs import ConfigError, maze_value, name_maze_file, network_value

    if nominal and for_colony:
        typer.echo("error: --nominal and --for-colony choose opposite worlds: give one", err=True)
        raise typer.Exit(2)
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
    try:
        maze_text = None if maze is None else maze_value(maze)
        spec = None if network is None else network_value(network)
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    flags = {
        "population": population,
        "generations": generations,
        "trials": trials,
        "steps": steps,
        "seed": seed,
        "maze": maze_text,
        "network": spec if spec is None or isinstance(spec, str) else spec.model_dump(mode="json"),
        "reality_gap": "off" if nominal else "colony" if for_colony else None,
        "job_size": job_size,
        "strategy": strategy,
        "name": name,
        "tags": tags or None,
    }
    body.update({k: v for k, v in flags.items() if v is not None})
    run = call_server(
        ctx, server, token, "POST", "/api/runs", body, explain=lambda d: name_maze_file(d, maze)
    )
    if follow:
        _follow(ctx, server, token, run["id"], as_json)
    elif as_json:
        print_json(run)
    else:
        typer.echo(f"run {run['id']} {run['status']}")


def stopped_following(what: str, command: str, server: str) -> NoReturn:
    """Ctrl-C during a follow: the thing followed carries on; name the command that
    re-attaches, and exit 130 (the shell's status for SIGINT)."""
    again = command if server == DEFAULT_SERVER else f"{command} --server {server}"
    typer.echo(f"stopped following {what}; it carries on. Re-attach: {again}", err=True)
    raise typer.Exit(130)


def _follow(ctx: typer.Context, server: str, token: str | None, run_id: int, as_json: bool) -> None:
    """Follow a run to its end and print its outcome (a failed run's reason); exit status 1
    unless it completed. Ctrl-C stops following, not the run, and names the command that
    re-attaches."""
    with open_client(ctx, server, token) as client:
        try:
            run = follow_run(client, run_id, rich_console(stderr=as_json))
        except httpx.HTTPError as exc:
            typer.echo(f"error: lost {server}: {exc}", err=True)
            raise typer.Exit(1) from exc
        except KeyboardInterrupt:
            stopped_following(f"run {run_id}", f"colony run follow {run_id}", server)
    if as_json:
        print_json(run)
    if run["status"] == "failed":
        typer.echo(f"run {run['id']} failed: {run['error'] or 'no reason recorded'}", err=True)
    elif not as_json:
        typer.echo(f"run {run['id']} {run['status']}")
        for line in run_champion_lines(run):
            typer.echo(line)
    if run["status"] != "completed":
        raise typer.Exit(1)


@run_app.command("follow")
def run_follow(
    ctx: typer.Context,
    run_id: int,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """A progress bar of a run until it ends, then its outcome (a failed run's reason).

    Exit status 1 unless the run completes."""
    _follow(ctx, server, token, run_id, as_json)


@run_app.command("list")
def run_list(
    ctx: typer.Context,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Every run, newest first."""
    runs = call_server(ctx, server, token, "GET", "/api/runs")
    if as_json:
        print_json(runs)
    else:
        rich_console().print(runs_table(runs, "runs"))


SHOWN_GENERATIONS = 10
"""Generations `colony run show` lists without --all-generations: evenly spaced, with the best."""


def shown_generations(generations: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """About SHOWN_GENERATIONS evenly spaced generations, always the first, the last and the
    one whose best reached the best training fitness so far."""
    n = len(generations)
    if n <= SHOWN_GENERATIONS:
        return generations
    picked = {round(k * (n - 1) / (SHOWN_GENERATIONS - 1)) for k in range(SHOWN_GENERATIONS)}
    finite = [k for k, g in enumerate(generations) if g["best"] is not None]
    if finite:
        picked.add(max(finite, key=lambda k: generations[k]["best"]))
    return [generations[k] for k in sorted(picked)]


@run_app.command("show")
def run_show(
    ctx: typer.Context,
    run_id: int,
    all_generations: Annotated[
        bool,
        typer.Option(
            "--all-generations",
            help=f"list every generation, not about {SHOWN_GENERATIONS} of them",
        ),
    ] = False,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """One run, its champion with the champion's held-out test, and its training fitness per
    generation (about ten generations: the first, the last, the best, evenly between)."""
    run = call_server(ctx, server, token, "GET", f"/api/runs/{run_id}")
    generations = call_server(ctx, server, token, "GET", f"/api/runs/{run_id}/generations")
    if as_json:
        print_json({**run, "history": generations})
        return
    console = rich_console()
    console.print(runs_table([run], f"run {run_id}"))
    if run["error"]:
        console.print(f"{run['status']}: {run['error']}", highlight=False)
    for line in run_champion_lines(run):
        console.print(line, highlight=False)
    shown = generations if all_generations else shown_generations(generations)
    title = "training fitness per generation"
    if len(shown) < len(generations):
        title += f" ({len(shown)} of {len(generations)}; --all-generations lists every one)"
    table = Table(title=title)
    for column in ("generation", "best of generation", "mean", "worst"):
        table.add_column(column)
    for g in shown:
        table.add_row(str(g["generation"]), cell(g["best"]), cell(g["mean"]), cell(g["worst"]))
    console.print(table)


@run_app.command("export")
def run_export(
    ctx: typer.Context,
    run_id: int,
    out: Annotated[Path, typer.Option("--out", help="directory for the files (created)")],
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
) -> None:
    """The run's generations and its latest generation's individuals, as CSV and Parquet, with
    its config.json and best.json (a completed run's champion) as `colony evolve` writes them."""
    from colony.export import export_run

    run = call_server(ctx, server, token, "GET", f"/api/runs/{run_id}")
    study = None
    if run.get("study_id") is not None:
        study = call_server(ctx, server, token, "GET", f"/api/studies/{run['study_id']}")["name"]
    best = None
    if run["generation"] > 0:  # a best controller exists once a generation is committed
        best = request(ctx, server, token, "GET", f"/api/runs/{run_id}/best").content
    try:
        with fetching(ctx, server, token) as fetch:
            written = export_run(run, study, fetch, out, best)
    except OSError as exc:
        typer.echo(f"error: cannot write {out}: {exc}", err=True)
        raise typer.Exit(1) from exc
    for path in written:
        typer.echo(str(path))


@run_app.command("archive")
def run_archive(
    ctx: typer.Context,
    run_id: int,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """The archive of a map-elites, cma-me or novelty run: each entry's descriptors, fitness and
    controller sha256 (push one with `colony robot push ROBOT --run ID --elite K`)."""
    archive = call_server(ctx, server, token, "GET", f"/api/runs/{run_id}/archive")
    if as_json:
        typer.echo(json.dumps(archive, indent=2))
        return
    axes = archive["axes"]
    table = Table(title=f"run {run_id}: archive after {archive['generation']} generations")
    for column in ("elite", *axes, "fitness", "sha256"):
        table.add_column(column)
    for k, elite in enumerate(archive["cells"]):
        table.add_row(
            str(k),
            *(f"{v:.3f}" for v in elite["descriptors"]),
            "-" if elite["fitness"] is None else f"{elite['fitness']:.3f}",
            elite["sha256"],
        )
    rich_console().print(table)


@run_app.command("best")
def run_best(
    ctx: typer.Context,
    run_id: int,
    out: Annotated[Path, typer.Option("--out", help="the controller document's file")],
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
) -> None:
    """Save the run's best controller document (a completed run's validated champion), byte
    for byte as the server sends it."""
    response = request(ctx, server, token, "GET", f"/api/runs/{run_id}/best")
    try:
        out.write_bytes(response.content)
    except OSError as exc:
        typer.echo(f"error: cannot write {out}: {exc}", err=True)
        raise typer.Exit(1) from exc
    typer.echo(f"{out}: {response.json()['sha256']}")


def _steer(ctx: typer.Context, server: str, token: str | None, run_id: int, action: str) -> None:
    run = call_server(ctx, server, token, "POST", f"/api/runs/{run_id}/{action}")
    typer.echo(f"run {run['id']} {run['status']}")


@run_app.command("pause")
def run_pause(
    ctx: typer.Context, run_id: int, server: ServerOpt = DEFAULT_SERVER, token: TokenOpt = None
) -> None:
    """Stop handing out the run's jobs (jobs in hand finish)."""
    _steer(ctx, server, token, run_id, "pause")


@run_app.command("resume")
def run_resume(
    ctx: typer.Context, run_id: int, server: ServerOpt = DEFAULT_SERVER, token: TokenOpt = None
) -> None:
    """Continue a paused run, or a failed one from its last stored generation."""
    _steer(ctx, server, token, run_id, "resume")


@run_app.command("cancel")
def run_cancel(
    ctx: typer.Context, run_id: int, server: ServerOpt = DEFAULT_SERVER, token: TokenOpt = None
) -> None:
    """End a run for good; its committed generations stay."""
    _steer(ctx, server, token, run_id, "cancel")


@run_app.command("delete")
def run_delete(
    ctx: typer.Context, run_id: int, server: ServerOpt = DEFAULT_SERVER, token: TokenOpt = None
) -> None:
    """Delete a finished run with its generations (a live one is cancelled first: not
    undoable)."""
    request(ctx, server, token, "DELETE", f"/api/runs/{run_id}")
    typer.echo(f"run {run_id} deleted")
