"""`colony server`: the central server (FastAPI, the run manager, zenoh), and the registration of
every REST client command on the root CLI."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from colony.robot_cli import robot_app, robots_command, status, workers_command
from colony.run_cli import run_app

if TYPE_CHECKING:
    from server.core.settings import Settings


def serve(
    db: Annotated[
        str | None,
        typer.Option("--db", help="SQLAlchemy URL [COLONY_DB_URL; default: sqlite:///colony.db]"),
    ] = None,
    host: Annotated[
        str | None, typer.Option(help="bind address [COLONY_HOST; default: 127.0.0.1]")
    ] = None,
    port: Annotated[int | None, typer.Option(help="HTTP port [COLONY_PORT; default: 8000]")] = None,
    zenoh_listen: Annotated[
        list[str] | None,
        typer.Option(
            "--zenoh-listen",
            help="zenoh endpoint to listen on, repeatable (off loopback it needs a lab's users "
            "and roles) [COLONY_ZENOH_LISTEN, a JSON list; default: tcp/127.0.0.1:7447]",
        ),
    ] = None,
    zenoh_connect: Annotated[
        list[str] | None,
        typer.Option(
            "--zenoh-connect",
            help="a lab zenohd to join, e.g. tcp/HOST:7447; repeatable [COLONY_ZENOH_CONNECT; "
            "default: none]",
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="local worker processes; 0 waits for remote ones [COLONY_WORKERS; "
            "default: one per spare core]"
        ),
    ] = None,
    no_zenoh: Annotated[
        bool,
        typer.Option(
            "--no-zenoh",
            help="no zenoh at all: evaluate in-process threads (--executors) [COLONY_ZENOH=false]",
        ),
    ] = False,
    executors: Annotated[
        int | None,
        typer.Option(
            help="in-process evaluation threads [COLONY_EXECUTORS; "
            "default: 0 with zenoh, 1 with --no-zenoh]"
        ),
    ] = None,
    log_level: Annotated[
        str | None,
        typer.Option(help="DEBUG, INFO, WARNING or ERROR [COLONY_LOG_LEVEL; default: INFO]"),
    ] = None,
    log_format: Annotated[
        str | None,
        typer.Option(
            help="text, or json for one JSON object per line [COLONY_LOG_FORMAT; default: text]"
        ),
    ] = None,
    token: Annotated[
        str | None,
        typer.Option(
            "--token",
            help="API bearer token, required off loopback [COLONY_API_TOKEN; "
            "default: none, writes from loopback only]",
        ),
    ] = None,
    read_closed: Annotated[
        bool,
        typer.Option(
            "--read-closed",
            help="reads need the token too [COLONY_READ_OPEN=false; default: reads are open]",
        ),
    ] = False,
    server_key: Annotated[
        Path | None,
        typer.Option(
            help="Ed25519 key signing robot pushes [COLONY_SERVER_KEY; "
            "default: server-key.pem beside the SQLite file]"
        ),
    ] = None,
    zenoh_users: Annotated[
        Path | None,
        typer.Option(
            help="zenoh user:password file clients must match [COLONY_ZENOH_USERS_FILE; "
            "default: none, loopback only]"
        ),
    ] = None,
    zenoh_roles: Annotated[
        Path | None,
        typer.Option(
            help="JSON of zenoh users per role (colony lab init) [COLONY_ZENOH_ROLES_FILE]"
        ),
    ] = None,
    zenoh_tls_cert: Annotated[
        Path | None,
        typer.Option(help="PEM certificate for tls/ endpoints [COLONY_ZENOH_TLS_CERTIFICATE]"),
    ] = None,
    zenoh_tls_key: Annotated[
        Path | None, typer.Option(help="its PEM private key [COLONY_ZENOH_TLS_PRIVATE_KEY]")
    ] = None,
    replacement: Annotated[
        str | None,
        typer.Option(
            help="what a stuck robot without its own policy gets: off or rank "
            "[COLONY_REPLACEMENT; default: rank]"
        ),
    ] = None,
    maze: Annotated[
        str | None,
        typer.Option(
            help="the lab maze the Colony page maps robots in: NAME, gen:SIZE:SEED or FILE "
            "[COLONY_MAZE; default: paper]"
        ),
    ] = None,
) -> None:
    """Run the colony server: REST API (OpenAPI at /docs), store, run manager, zenoh router
    for workers (docs/protocol.md) and N local workers."""
    import uvicorn

    from server.app import create_app
    from server.core.auth import check_bind
    from server.core.settings import Settings

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

    from server.core.db import ServerLock, StoreUnusableError, check_sqlite_file

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
        from server.core.logs import configure

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


def register(app: typer.Typer) -> None:
    """Add `server`, `run`, `status`, `workers`, `robots` and `robot` to the root CLI."""
    app.command(name="server")(serve)
    app.add_typer(run_app, name="run")
    app.command(name="status")(status)
    app.command(name="workers")(workers_command)
    app.command(name="robots")(robots_command)
    app.add_typer(robot_app, name="robot")
