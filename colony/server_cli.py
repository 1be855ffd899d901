"""`colony server` (the central server) and its REST clients: `colony run ...`, `colony status`.

The clients speak only the documented REST API (docs/api.md) through httpx; tests inject a
transport with `app(args, obj={"transport": ...})`. Server errors print the server's message
and exit non-zero.
"""

from __future__ import annotations

import itertools
import json
import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import httpx
import typer
from rich.console import Console
from rich.table import Table

from colony.options import NominalOpt

if TYPE_CHECKING:
    from server.settings import Settings

DEFAULT_SERVER = "http://127.0.0.1:8000"
TIMEOUT_S = 30.0
FOLLOW_POLL_S = 0.2
FINAL = ("completed", "failed", "cancelled")
SHORT_SHA = 12
"""Tables show a sha256 by its first 12 hex digits, a prefix every sha option accepts."""

ServerOpt = Annotated[str, typer.Option("--server", help="server base URL")]
TokenOpt = Annotated[
    str | None,
    typer.Option("--token", envvar="COLONY_API_TOKEN", help="API bearer token [COLONY_API_TOKEN]"),
]
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
            help="zenoh endpoint to listen on, repeatable (default tcp/127.0.0.1:7447; off "
            "loopback it needs a lab's users and roles) [COLONY_ZENOH_LISTEN, a JSON list]",
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
            "--no-zenoh",
            help="no zenoh at all: evaluate in-process threads (--executors) [COLONY_ZENOH]",
        ),
    ] = False,
    executors: Annotated[
        int | None,
        typer.Option(
            help="in-process evaluation threads (default: 0 with zenoh, 1 with --no-zenoh) "
            "[COLONY_EXECUTORS]"
        ),
    ] = None,
    log_level: Annotated[
        str | None, typer.Option(help="DEBUG, INFO, WARNING or ERROR [COLONY_LOG_LEVEL]")
    ] = None,
    log_format: Annotated[
        str | None,
        typer.Option(help="text, or json for one JSON object per line [COLONY_LOG_FORMAT]"),
    ] = None,
    token: Annotated[
        str | None,
        typer.Option("--token", help="API bearer token, required off loopback [COLONY_API_TOKEN]"),
    ] = None,
    read_closed: Annotated[
        bool, typer.Option("--read-closed", help="reads need the token too [COLONY_READ_OPEN]")
    ] = False,
    server_key: Annotated[
        Path | None,
        typer.Option(help="Ed25519 key signing robot pushes [COLONY_SERVER_KEY]"),
    ] = None,
    zenoh_users: Annotated[
        Path | None,
        typer.Option(help="zenoh user:password file clients must match [COLONY_ZENOH_USERS_FILE]"),
    ] = None,
    zenoh_roles: Annotated[
        Path | None,
        typer.Option(
            help="JSON of zenoh users per role (colony lab init) [COLONY_ZENOH_ROLES_FILE]"
        ),
    ] = None,
    zenoh_tls_cert: Annotated[
        Path | None, typer.Option(help="PEM certificate for tls/ endpoints")
    ] = None,
    zenoh_tls_key: Annotated[Path | None, typer.Option(help="its PEM private key")] = None,
    replacement: Annotated[
        str | None,
        typer.Option(
            help="what a stuck robot without its own policy gets: off or rank [COLONY_REPLACEMENT]"
        ),
    ] = None,
    maze: Annotated[
        str | None,
        typer.Option(
            help="the lab maze the Colony page maps robots in: NAME, gen:SIZE:SEED or FILE "
            "(default paper) [COLONY_MAZE]"
        ),
    ] = None,
) -> None:
    """Run the colony server: REST API (OpenAPI at /docs), store, run manager, zenoh router
    for workers (docs/protocol.md) and N local workers."""
    import uvicorn

    from server.app import create_app
    from server.auth import check_bind
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
        "log_level": log_level.upper() if log_level else None,
        "log_format": log_format,
        "api_token": token,
        "read_open": False if read_closed else None,
        "server_key": server_key,
        "zenoh_users_file": zenoh_users,
        "zenoh_roles_file": zenoh_roles,
        "zenoh_tls_certificate": zenoh_tls_cert,
        "zenoh_tls_private_key": zenoh_tls_key,
        "replacement": replacement,
        "maze": maze,
    }
    try:
        settings = Settings.model_validate({k: v for k, v in overrides.items() if v is not None})
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    try:
        check_bind(settings.host, settings.api_token)
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    try:  # every setting checked before the store is opened or a port bound
        app = create_app(settings)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    taken = _taken_ports(settings)
    if taken:
        typer.echo(f"error: {taken}", err=True)
        raise typer.Exit(1)
    from sqlalchemy.exc import OperationalError

    from server.db import ServerLock, StoreUnusableError, check_sqlite_file

    # one line and a non-zero exit, so a restart policy shows why (docs/reliability.md)
    try:
        lock = ServerLock.acquire(settings.db_url)
    except StoreUnusableError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    except OperationalError as exc:
        typer.echo(f"error: cannot reach the database: {str(exc.orig).strip()}", err=True)
        raise typer.Exit(1) from exc
    try:
        check_sqlite_file(settings.db_url)
        key_path = settings.server_key_path() or "an in-memory key"
        typer.echo(f"robot pushes are signed with {key_path}")
        from server.logs import configure

        configure(settings.log_level, settings.log_format)
        uvicorn.run(app, host=settings.host, port=settings.port, log_config=None)
    except StoreUnusableError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    finally:
        lock.close()


def _taken_ports(settings: Settings) -> str | None:
    """Why the HTTP port or a TCP zenoh endpoint to listen on cannot be bound (another server
    holds it?), checked before anything starts; None when all can."""
    wanted: list[tuple[str, str, str, int]] = [("HTTP", "--port", settings.host, settings.port)]
    if settings.zenoh:
        for endpoint in settings.zenoh_listen:
            proto, _, address = endpoint.partition("/")
            host, _, port = address.split("?")[0].split("#")[0].rpartition(":")
            if proto in ("tcp", "tls") and port.isdigit():
                wanted.append((f"zenoh {endpoint}", "--zenoh-listen", host.strip("[]"), int(port)))
    for what, flag, host, number in wanted:
        if number == 0:
            continue
        try:
            family = socket.getaddrinfo(host, number, type=socket.SOCK_STREAM)[0][0]
            with socket.socket(family, socket.SOCK_STREAM) as sock:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind((host, number))
        except OSError as exc:
            return (
                f"cannot listen for {what} on {host}:{number}: {exc.strerror or exc} "
                f"(another colony server? choose another {flag})"
            )
    return None


def _client(ctx: typer.Context, server: str, token: str | None) -> httpx.Client:
    obj = ctx.find_root().obj
    transport = obj.get("transport") if isinstance(obj, dict) else None
    headers = {"Authorization": f"Bearer {token}"} if token else None
    # no redirects are followed, so a plain-http server never needs the CA bundle, whose
    # loading would cost every call ~20 ms
    verify = not server.startswith("http://")
    return httpx.Client(
        base_url=server.rstrip("/"),
        transport=transport,
        timeout=TIMEOUT_S,
        headers=headers,
        verify=verify,
    )


def _checked(response: httpx.Response, invalid_exit: int = 1) -> httpx.Response:
    """The response, or the server's error message and exit status 1 (`invalid_exit` for a
    422)."""
    if response.is_error:
        try:
            detail = response.json().get("detail", response.text)
        except ValueError:
            detail = response.text
        typer.echo(f"error {response.status_code}: {detail}", err=True)
        raise typer.Exit(invalid_exit if response.status_code == 422 else 1)
    return response


def request(
    ctx: typer.Context,
    server: str,
    token: str | None,
    method: str,
    path: str,
    body: Any = None,
    *,
    invalid_exit: int = 1,
) -> httpx.Response:
    """One request; on failure the server's error message and exit status 1 (`invalid_exit`
    for a 422)."""
    try:
        with _client(ctx, server, token) as client:
            response = client.request(method, path, json=body)
    except httpx.HTTPError as exc:
        typer.echo(f"error: cannot reach {server}: {exc}", err=True)
        raise typer.Exit(1) from exc
    return _checked(response, invalid_exit)


@contextmanager
def fetching(ctx: typer.Context, server: str, token: str | None) -> Iterator[Callable[[str], Any]]:
    """GET path -> JSON over one connection (exports make many requests); failures exit 1."""
    with _client(ctx, server, token) as client:

        def fetch(path: str) -> Any:
            try:
                response = client.get(path)
            except httpx.HTTPError as exc:
                typer.echo(f"error: cannot reach {server}: {exc}", err=True)
                raise typer.Exit(1) from exc
            return _checked(response).json()

        yield fetch


def call_server(
    ctx: typer.Context,
    server: str,
    token: str | None,
    method: str,
    path: str,
    body: Any = None,
) -> Any:
    """One request's JSON; the server's error message and exit status 1 on failure."""
    return request(ctx, server, token, method, path, body).json()


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


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


def _runs_table(runs: list[dict[str, Any]], title: str) -> Table:
    table = Table(title=title)
    for column in ("id", "name", "status", "network", "maze", "seed", "strategy", "study"):
        # on a narrow terminal the long texts fold; the status and numbers stay whole
        table.add_column(column, no_wrap=column in ("id", "status", "seed"), overflow="fold")
    table.add_column("generation", no_wrap=True)
    table.add_column("best", no_wrap=True)
    for run in runs:
        config = run["config"]
        table.add_row(
            str(run["id"]),
            _fmt(run.get("name")),
            run["status"],
            _network(config),
            _maze(config),
            str(run["seed"]),
            str(config.get("strategy") or "paper-ga"),
            _study(run),
            f"{run['generation']}/{run['generations']}",
            _fmt(run["best_fitness"]),
        )
    return table


def follow_run(
    client: httpx.Client,
    run_id: int,
    console: Console,
    alive: Callable[[], None] = lambda: None,
    poll_s: float = FOLLOW_POLL_S,
) -> dict[str, Any]:
    """A progress bar of committed generations with the best fitness, until the run ends
    (completed, failed or cancelled); returns the final RunOut. `alive` may raise to abort."""
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
            best = run["best_fitness"]
            text = f"run {run_id}" + ("" if best is None else f" best {best:.3f}")
            bar.update(
                task, total=run["generations"], completed=run["generation"], description=text
            )
            if run["status"] in FINAL:
                return run
            alive()
            tick.wait(poll_s)


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
    follow: Annotated[
        bool, typer.Option("--follow", help="show a progress bar until the run ends")
    ] = False,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Start a run; unset fields default to the paper's experiment (validated by the server).

    With --follow, exit status 1 unless the run completes."""
    from colony.run_inputs import ConfigError, maze_value, network_value

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
    }
    body.update({k: v for k, v in flags.items() if v is not None})
    run = call_server(ctx, server, token, "POST", "/api/runs", body)
    if follow:
        _follow(ctx, server, token, run["id"], as_json)
    elif as_json:
        _print_json(run)
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
    with _client(ctx, server, token) as client:
        try:
            run = follow_run(client, run_id, Console(stderr=as_json))
        except httpx.HTTPError as exc:
            typer.echo(f"error: lost {server}: {exc}", err=True)
            raise typer.Exit(1) from exc
        except KeyboardInterrupt:
            stopped_following(f"run {run_id}", f"colony run follow {run_id}", server)
    if as_json:
        _print_json(run)
    if run["status"] == "failed":
        typer.echo(f"run {run['id']} failed: {run['error'] or 'no reason recorded'}", err=True)
    elif not as_json:
        best = "" if run["best_fitness"] is None else f" best {run['best_fitness']:.4f}"
        typer.echo(f"run {run['id']} {run['status']}{best}")
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
        _print_json(runs)
    else:
        Console().print(_runs_table(runs, "runs"))


@run_app.command("show")
def run_show(
    ctx: typer.Context,
    run_id: int,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """One run with its fitness per generation."""
    run = call_server(ctx, server, token, "GET", f"/api/runs/{run_id}")
    generations = call_server(ctx, server, token, "GET", f"/api/runs/{run_id}/generations")
    if as_json:
        _print_json({**run, "history": generations})
        return
    console = Console()
    console.print(_runs_table([run], f"run {run_id}"))
    if run["error"]:
        console.print(f"{run['status']}: {run['error']}", highlight=False)
    table = Table(title="generations")
    for column in ("generation", "best", "mean", "worst"):
        table.add_column(column)
    for g in generations:
        table.add_row(str(g["generation"]), _fmt(g["best"]), _fmt(g["mean"]), _fmt(g["worst"]))
    console.print(table)


@run_app.command("export")
def run_export(
    ctx: typer.Context,
    run_id: int,
    out: Annotated[Path, typer.Option("--out", help="directory for the files (created)")],
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
) -> None:
    """The run's generations and its latest generation's individuals, as CSV and Parquet."""
    from colony.export import export_run

    run = call_server(ctx, server, token, "GET", f"/api/runs/{run_id}")
    study = None
    if run.get("study_id") is not None:
        study = call_server(ctx, server, token, "GET", f"/api/studies/{run['study_id']}")["name"]
    try:
        with fetching(ctx, server, token) as fetch:
            written = export_run(run, study, fetch, out)
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
    for k, cell in enumerate(archive["cells"]):
        table.add_row(
            str(k),
            *(f"{v:.3f}" for v in cell["descriptors"]),
            "-" if cell["fitness"] is None else f"{cell['fitness']:.3f}",
            cell["sha256"],
        )
    Console().print(table)


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


def workers_table(workers: list[dict[str, Any]]) -> Table:
    """Rows of GET /api/workers: evaluations are controllers whose fitness the server took,
    late ones those it dropped (a worker's own log counts both)."""
    table = Table(title="workers")
    for column in (
        "name", "host", "state", "evaluations", "late", "robot-steps/s", "last seen", "quarantined",
    ):  # fmt: skip
        table.add_column(column)
    for w in workers:
        speed = w["robot_steps_per_s"]
        table.add_row(
            w["name"],
            w["host"],
            w["state"],
            str(w["evaluations"]),
            str(w["late"]),
            "-" if speed is None else f"{speed:.0f}",
            ago(w["last_seen"]),
            "yes" if w.get("quarantined") else "-",
        )
    return table


def robots_table(robots: list[dict[str, Any]]) -> Table:
    """Rows of GET /api/robots or of /api/colony's robots (the same view)."""
    table = Table(title="robots")
    for column in (
        "id", "online", "state", "steps", "stuck", "controller", "replacement", "last seen",
    ):  # fmt: skip
        table.add_column(column)
    for r in robots:
        table.add_row(
            r["id"],
            "yes" if r["online"] else "no",
            r["state"],
            str(r["steps"]),
            str(r["stuck_events"]),
            (r["controller_sha256"] or "-")[:SHORT_SHA],
            _replacement(r),
            ago(r["last_seen"]),
        )
    return table


def ago(moment: str | None, now: datetime | None = None) -> str:
    """An ISO 8601 time as a person reads it in a table: "12 s ago", "3 h ago", "never"."""
    if moment is None:
        return "never"
    then = datetime.fromisoformat(moment)
    if then.tzinfo is None:
        then = then.replace(tzinfo=UTC)
    s = max(0.0, ((now or datetime.now(UTC)) - then).total_seconds())
    for unit, size in (("d", 86400), ("h", 3600), ("min", 60)):
        if s >= 2 * size:
            return f"{s / size:.0f} {unit} ago"
    return f"{s:.0f} s ago"


def _replacement(robot: dict[str, Any]) -> str:
    """`rank`, or `off (colony)` when the robot follows the colony's policy."""
    policy = str(robot["replacement"])
    return policy if robot["replacement_source"] == "robot" else f"{policy} (colony)"


def status(
    ctx: typer.Context,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Colony summary: runs by status, jobs, and tables of active runs, workers and robots."""
    colony = call_server(ctx, server, token, "GET", "/api/colony")
    if as_json:
        _print_json(colony)
        return
    console = Console()
    counts = ", ".join(f"{k} {v}" for k, v in sorted(colony["runs"].items())) or "none"
    jobs = colony["jobs"]
    console.print(f"runs: {counts}")
    console.print(
        f"jobs of the generations in flight: pending {jobs['pending']}, leased {jobs['leased']}, "
        f"done {jobs['done']}"
    )
    console.print(_runs_table(colony["active"], "active runs"))
    console.print(workers_table(colony["workers"]))
    console.print(robots_table(colony["robots"]))


def workers_command(
    ctx: typer.Context,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """The simulation workers the server knows (gone ones for a while)."""
    workers = call_server(ctx, server, token, "GET", "/api/workers")
    if as_json:
        _print_json(workers)
    else:
        Console().print(workers_table(workers))


def robots_command(
    ctx: typer.Context,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Every robot ever seen: online, state, steps, controller, replacement policy."""
    robots = call_server(ctx, server, token, "GET", "/api/robots")
    if as_json:
        _print_json(robots)
    else:
        Console().print(robots_table(robots))


robot_app = typer.Typer(help="Inspect and command one robot.", no_args_is_help=True)


@robot_app.command("show")
def robot_show(
    ctx: typer.Context,
    robot: str,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """One robot: state, controller origin, whiskers, stuck events, link."""
    detail = call_server(ctx, server, token, "GET", f"/api/robots/{robot}")
    if as_json:
        _print_json(detail)
        return
    for key in (
        "id", "online", "state", "steps", "stuck_events", "whiskers", "controller_sha256",
        "controller_run", "controller_rank", "controller_generation", "boot",
    ):  # fmt: skip
        typer.echo(f"{key:22s} {_fmt(detail[key])}")
    typer.echo(f"{'replacement':22s} {_replacement(detail)}")
    typer.echo(f"{'last seen':22s} {ago(detail['last_seen'])}")


POLICY_CHOICES = ("off", "rank", "archive", "fit", "colony")
"""`colony robot replacement` values; `colony` clears the robot's own policy."""


@robot_app.command("replacement")
def robot_replacement(
    ctx: typer.Context,
    robot: str,
    policy: Annotated[
        str, typer.Argument(help="off, rank, archive, fit, or colony (follow the colony's)")
    ],
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Set what this robot gets when it is stuck: off (nothing: it escapes and resumes its
    controller), rank (the next rank of its controller's run), or colony (the server's setting)."""
    if policy not in POLICY_CHOICES:
        raise typer.BadParameter(f"must be one of {', '.join(POLICY_CHOICES)}", param_hint="POLICY")
    body = {"policy": None if policy == "colony" else policy}
    detail = call_server(ctx, server, token, "PUT", f"/api/robots/{robot}/replacement", body)
    if as_json:
        _print_json(detail)
    else:
        typer.echo(f"robot {robot} replacement: {_replacement(detail)}")


@robot_app.command("stuck")
def robot_stuck(
    ctx: typer.Context,
    robot: str,
    limit: Annotated[int, typer.Option(help="newest events")] = 50,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """The robot's stuck events: the policy that served each, what was sent, and the steps it
    then ran before its next stuck event."""
    ledger = call_server(ctx, server, token, "GET", f"/api/robots/{robot}/stuck?limit={limit}")
    if as_json:
        _print_json(ledger)
        return
    table = Table(title=f"stuck events of {robot}")
    for column in ("step", "reason", "controller", "policy", "replacement", "steps run"):
        table.add_column(column)
    for e in ledger["events"]:
        table.add_row(
            _fmt(e["step"]),
            e["reason"],
            (e["controller_sha256"] or "-")[:SHORT_SHA],
            _fmt(e["policy"]),
            (e["replacement_sha256"] or "-")[:SHORT_SHA],
            _fmt(e["steps_run"]),
        )
    Console().print(table)
    runs = Table(title=f"controllers in these events of {robot}")
    for column in ("controller", "time run", "stuck events", "stuck per hour"):
        runs.add_column(column)
    for c in ledger.get("controllers", []):
        hours = c["seconds_run"] / 3600
        runs.add_row(
            c["sha256"][:SHORT_SHA],
            f"{c['seconds_run']:.0f} s",
            str(c["stuck_events"]),
            f"{c['stuck_events'] / hours:.0f}" if hours > 0 else "-",
        )
    Console().print(runs)


CALIBRATION_POSES = ("sim", "tracker")
"""Pose sources a calibration may use: measured outside the robot's model, never odometry."""


@robot_app.command("calibrate")
def robot_calibrate(
    ctx: typer.Context,
    robot: str,
    since: Annotated[
        str | None,
        typer.Option(help="only samples from this time on (ISO 8601, e.g. 2026-12-03T10:00)"),
    ] = None,
    limit: Annotated[int, typer.Option(help="newest samples fetched")] = 36_000,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Fit the robot's whisker ranges and wheel gains from its traces with poses (emulator or
    tracker, never odometry) in the lab maze, and store them with the robot."""
    import numpy as np

    from evorobotics.calibrate import CalibrationError, calibrate
    from evorobotics.maze import parse_maze
    from schemas.world import World

    try:
        start = None if since is None else datetime.fromisoformat(since).timestamp()
    except ValueError:
        raise typer.BadParameter(f"--since {since!r} is not an ISO 8601 time") from None
    samples = call_server(ctx, server, token, "GET", f"/api/robots/{robot}/traces?limit={limit}")[
        "samples"
    ]
    kept = [
        x
        for x in samples
        if x["pose"] is not None
        and x["pose_source"] in CALIBRATION_POSES
        and (start is None or (x["at"] is not None and x["at"] >= start))
    ]
    if not kept:
        odometry = any(x["pose_source"] == "odometry" for x in samples)
        why = "only odometry, which cannot calibrate the physics it assumes" if odometry else "none"
        typer.echo(f"colony robot calibrate: {robot} has no samples with poses: {why}", err=True)
        raise typer.Exit(2)
    maze = call_server(ctx, server, token, "GET", "/api/colony/map?samples=1")["maze"]
    follows = np.array(
        [
            b["boot"] == a["boot"] and b["step"] == a["step"] + 1
            for a, b in itertools.pairwise(kept)
        ],
        dtype=bool,
    )
    try:
        fit = calibrate(
            parse_maze("\n".join(maze["rows"]), maze["name"], maze["cell_size"]),
            np.array([x["pose"] for x in kept]),
            np.array([[int(c) for c in x["whiskers"]] for x in kept]),
            np.array([x["motors"] for x in kept]),
            World(),
            follows,
        )
    except CalibrationError as exc:
        typer.echo(f"colony robot calibrate: {robot}: {exc}; nothing stored", err=True)
        raise typer.Exit(2) from None
    stored = call_server(
        ctx, server, token, "POST", f"/api/robots/{robot}/calibration", fit.as_dict()
    )
    if as_json:
        _print_json(stored)
        return
    c = stored["calibration"]
    table = Table(title=f"calibration of {robot} from {c['samples']} samples")
    for column in ("", "left", "", "centre", "", "right"):
        table.add_column(column, justify="right")
    ranges = [f"{1000 * r:.1f}" for r in c["whisker_range"]]
    errs = [f"+-{1000 * e:.1f}" for e in c["uncertainty"]["whisker_range"]]
    table.add_row("whisker range, mm", *ranges)
    table.add_row("uncertainty, mm", *errs)
    Console().print(table)
    for k in c.get("bounded", []):
        middle, half = c["whisker_range"][k], c["uncertainty"]["whisker_range"][k]
        typer.echo(
            f"whisker {k} read the same bit throughout: its range lies in "
            f"[{1000 * (middle - half):.1f}, {1000 * (middle + half):.1f}] mm"
        )
    gains, gain_errs = c["motor_gain"], c["uncertainty"]["motor_gain"]
    typer.echo(
        f"wheel gains: left {gains[0]:.4f} +- {gain_errs[0]:.1g}, right {gains[1]:.4f} +- "
        f"{gain_errs[1]:.1g}; pose residual {c['residuals']['pose_rms_m']:.2g} m over "
        f"{c['residuals']['moving_steps']} moving steps; stored for {robot}"
    )


def _pushed(result: dict[str, Any], as_json: bool) -> None:
    if as_json:
        _print_json(result)
    elif result["accepted"]:
        typer.echo(f"robot {result['robot']} runs {_fmt(result['sha256'])}")
    else:
        why = result["reason"] or ("no acknowledgement" if not result["acknowledged"] else "")
        typer.echo(f"robot {result['robot']} refused: {why}", err=True)
    if not result["accepted"]:
        raise typer.Exit(1)


@robot_app.command("push")
def robot_push(
    ctx: typer.Context,
    robot: str,
    run: Annotated[int | None, typer.Option("--run", help="push this run's individual")] = None,
    rank: Annotated[
        int | None,
        typer.Option(help="training rank in the run's latest generation (default: its best)"),
    ] = None,
    elite: Annotated[
        int | None,
        typer.Option(help="entry of the run's archive (colony run archive; QD runs)"),
    ] = None,
    fit: Annotated[
        bool,
        typer.Option(
            "--fit",
            help="the run's candidate that roams most in the robot's calibrated world "
            "(colony robot calibrate)",
        ),
    ] = False,
    sha: Annotated[
        str | None,
        typer.Option("--sha", help="push a stored controller: its sha256 or a prefix of 8+ digits"),
    ] = None,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Push a run's best (--run: its validated champion once completed), a training rank of its
    latest generation (--run --rank N), an entry of its archive (--run --elite K), its candidate
    that roams most in the robot's calibrated world (--run --fit), or a stored controller (--sha).

    Exit status 1 unless the robot accepted it."""
    if (run is None) == (sha is None):
        raise typer.BadParameter("give exactly one of --run or --sha")
    body: dict[str, Any] = {"sha256": sha}
    if run is not None:
        body = {"run_id": run, "rank": rank, "elite": elite, "fit": fit}
    _pushed(
        call_server(ctx, server, token, "POST", f"/api/robots/{robot}/controller", body), as_json
    )


@robot_app.command("stop")
def robot_stop(
    ctx: typer.Context,
    robot: str,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Motors to zero until the next push."""
    _pushed(call_server(ctx, server, token, "POST", f"/api/robots/{robot}/stop"), as_json)


def register(app: typer.Typer) -> None:
    """Add `server`, `run`, `status`, `workers`, `robots` and `robot` to the root CLI."""
    app.command(name="server")(serve)
    app.add_typer(run_app, name="run")
    app.command(name="status")(status)
    app.command(name="workers")(workers_command)
    app.command(name="robots")(robots_command)
    app.add_typer(robot_app, name="robot")


def robot_forget(
    ctx: typer.Context,
    robot: str,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
) -> None:
    """Forget a stale robot: its entry, last report, stuck events and traces (stop its agent
    first; the controllers' field statistics stay)."""
    try:
        with _client(ctx, server, token) as client:
            response = client.delete(f"/api/robots/{robot}")
    except httpx.HTTPError as exc:
        typer.echo(f"error: cannot reach {server}: {exc}", err=True)
        raise typer.Exit(1) from exc
    if response.is_error:
        typer.echo(f"error {response.status_code}: {response.json().get('detail')}", err=True)
        raise typer.Exit(1)
    typer.echo(f"robot {robot} forgotten")


robot_app.command("forget")(robot_forget)
