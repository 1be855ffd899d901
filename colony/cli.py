"""Root of the `colony` CLI. Each role's subcommands live in their own module and are added here."""

from __future__ import annotations

import logging
import os
import sys
from typing import NoReturn

import typer

from colony.agent_cli import register as register_agent_commands
from colony.analyze_cli import analyze_command
from colony.db_cli import db_app
from colony.demo import demo_command
from colony.evaluate_cli import evaluate_command
from colony.evolve import evolve_command
from colony.lab_cli import lab_app
from colony.mazes_cli import mazes_command
from colony.server_cli import register as register_server_commands
from colony.study_cli import study_app
from colony.worker_cli import worker_command

app = typer.Typer(
    name="colony",
    help="EvoColony: evolve neural controllers for EvBots in simulation and run them on a colony.",
    no_args_is_help=True,
    add_completion=False,
)


@app.command()
def presets() -> None:
    """List the named network presets with their weight counts."""
    from schemas.network import PRESETS

    for name, spec in PRESETS.items():
        depth = spec.recurrence
        per_layer = list(depth) if isinstance(depth, tuple) else depth
        typer.echo(
            f"{name:16s} {spec.weight_count:6d} weights  hidden={list(spec.hidden)} "
            f"T={spec.delays} S={per_layer} out={spec.output_activation}"
        )


app.command(name="demo")(demo_command)
app.command(name="evolve")(evolve_command)
app.command(name="mazes")(mazes_command)
register_server_commands(app)
app.command(name="worker")(worker_command)
register_agent_commands(app)
app.command(name="analyze")(analyze_command)
app.command(name="evaluate")(evaluate_command)
app.add_typer(db_app, name="db")
app.add_typer(lab_app, name="lab")
app.add_typer(study_app, name="study")


def main() -> None:
    """Run the command; a process that imported zenoh ends with `_exit_now`."""
    try:
        app()
    except SystemExit as exc:
        if "zenoh" in sys.modules:
            _exit_now(exc.code)
        raise


def _exit_now(code: object) -> NoReturn:
    """Exit as SystemExit(code) would, with logs and output flushed but without finalizing
    the interpreter: zenoh's own threads log through Python, and one that does so while the
    interpreter finalizes aborts the process (SIGABRT, "FATAL: exception not rethrown"), which
    turned an agent's clean Ctrl-C into a crash now and then."""
    if isinstance(code, str):
        print(code, file=sys.stderr)
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code if isinstance(code, int) else 0 if code is None else 1)
