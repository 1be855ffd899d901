"""`colony worker`: a simulation worker that takes evaluation jobs from a server until stopped."""

from __future__ import annotations

import threading
from typing import Annotated

import typer

from colony.options import LogFormatOpt, LogLevelOpt, ZenohPasswordOpt, ZenohRootCaOpt, ZenohUserOpt


def worker_command(
    connect: Annotated[
        list[str],
        typer.Option(
            "--connect",
            envvar="COLONY_CONNECT",
            help="zenoh endpoint of the server (or a lab zenohd), e.g. tcp/SERVER:7447; repeatable",
        ),
    ] = ["tcp/127.0.0.1:7447"],  # noqa: B006 - typer reads the default, never mutates it
    name: Annotated[
        str | None,
        typer.Option(help="worker name in GET /api/workers (default: [ZENOH_USER.]hostname-pid)"),
    ] = None,
    threads: Annotated[
        int,
        typer.Option(
            min=1,
            max=256,
            help="threads a job's evaluation runs on (the same results whatever the count): "
            "a machine's cores for its one worker",
        ),
    ] = 1,
    zenoh_user: ZenohUserOpt = None,
    zenoh_password: ZenohPasswordOpt = None,
    zenoh_root_ca: ZenohRootCaOpt = None,
    log_level: LogLevelOpt = "INFO",
    log_format: LogFormatOpt = "text",
    exit_with_parent: Annotated[
        bool,
        typer.Option(
            "--exit-with-parent",
            help="stop when the parent process dies (set for `colony server --workers N`)",
        ),
    ] = False,
) -> None:
    """Pull evaluation jobs over zenoh and evaluate them; Ctrl-C finishes the current job."""
    from schemas.security import ZenohClientAuth
    from server.core.logs import as_format, configure
    from worker.main import (
        WorkerSettings,
        default_name,
        install_signal_handlers,
        run_worker,
        watch_parent,
    )

    try:
        auth = ZenohClientAuth(user=zenoh_user, password=zenoh_password, root_ca=zenoh_root_ca)
        settings = WorkerSettings(
            connect=tuple(connect), name=name or default_name(auth.user), auth=auth, threads=threads
        )
        configure(log_level, as_format(log_format), ids={"worker": settings.name})
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    stop = threading.Event()
    install_signal_handlers(stop)
    if exit_with_parent:
        watch_parent(stop)
    stats = run_worker(settings, stop)
    typer.echo(
        f"worker {settings.name}: {stats.evaluations} evaluations in {stats.jobs_done} jobs, "
        f"{stats.errors} errors"
    )
