"""`colony lab init`: a lab's credentials, keys and certificates (docs/deployment.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

lab_app = typer.Typer(
    help="Set up a lab: credentials per worker, robot and tracker, keys, TLS.", no_args_is_help=True
)


@lab_app.command(name="init")
def init_command(
    directory: Annotated[Path, typer.Argument(help="where to write (must not exist or be empty)")],
    server_host: Annotated[
        str, typer.Option(help="name or address workers and robots reach the server at")
    ],
    robot: Annotated[
        list[str] | None,
        typer.Option("--robot", help="a robot id, repeatable (default evbot-1..N)"),
    ] = None,
    robots: Annotated[int, typer.Option(min=0, max=1000, help="evbot-1..N without --robot")] = 8,
    worker: Annotated[
        list[str] | None,
        typer.Option("--worker", help="a worker host's name, repeatable (default worker-1..N)"),
    ] = None,
    workers: Annotated[int, typer.Option(min=0, max=1000, help="workers without --worker")] = 2,
    tracker: Annotated[
        list[str] | None,
        typer.Option("--tracker", help="an overhead tracker's name, repeatable (default tracker)"),
    ] = None,
    tls: Annotated[
        bool, typer.Option("--tls", help="zenoh over TLS: a CA and a certificate")
    ] = False,
    port: Annotated[int, typer.Option(min=2, max=65535, help="the server's zenoh port")] = 7447,
    paths_as: Annotated[
        Path | None,
        typer.Option(help="the directory as the processes see it (e.g. a container's /lab)"),
    ] = None,
) -> None:
    """Write zenoh users and roles, the API token, the signing key, TLS files and env files."""
    from server.core.lab import init_lab

    try:
        lab = init_lab(
            directory,
            workers=worker or [f"worker-{i}" for i in range(1, workers + 1)],
            robots=robot or [f"evbot-{i}" for i in range(1, robots + 1)],
            trackers=tracker or ["tracker"],
            server_host=server_host,
            tls=tls,
            port=port,
            paths_as=paths_as,
        )
    except (ValueError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(f"lab credentials in {lab.root} (secrets are mode 600: copy each env file only")
    typer.echo("to its host). Start each process with its env file:")
    typer.echo(f"  server:     env $(cat {lab.server_env}) colony server")
    for path in lab.worker_envs.values():
        typer.echo(f"  a worker:   env $(cat {path}) colony worker")
    for path in lab.robot_envs.values():
        typer.echo(f"  a robot:    env $(cat {path}) colony agent --serial /dev/ttyS0")
    for path in lab.tracker_envs.values():
        typer.echo(f"  a tracker:  env $(cat {path}) (your tracker's bridge; docs/robots.md)")
