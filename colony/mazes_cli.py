"""`colony mazes`: the shipped mazes (or one named maze) as a table, or one rendered to PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def mazes_command(
    maze: Annotated[
        str | None,
        typer.Argument(
            metavar="NAME_OR_FILE",
            help="one maze: shipped name, gen:SIZE:SEED or maze file (default: every shipped one)",
        ),
    ] = None,
    png: Annotated[
        Path | None, typer.Option("--png", metavar="FILE", help="draw NAME_OR_FILE into this PNG")
    ] = None,
) -> None:
    """The shipped mazes: size, free cells, steps of one crossing and what each is for; with
    --png, draw one (walls in metres)."""
    from rich.table import Table

    from colony.client import rich_console
    from evorobotics.errors import EvoError
    from evorobotics.evaluate import crossing_steps
    from evorobotics.maze import load_maze, maze_names, maze_note

    if png is not None and maze is None:
        raise typer.BadParameter("name the maze to render, e.g. colony mazes paper --png paper.png")
    specs = maze_names() if maze is None else [maze]
    try:
        loaded = [load_maze(spec) for spec in specs]
    except (EvoError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    if png is not None:
        from evorobotics.plots import maze_plot  # matplotlib only when drawing

        try:
            maze_plot(loaded[0], png)
        except OSError as exc:
            typer.echo(f"error: cannot write {png}: {exc.strerror}", err=True)
            raise typer.Exit(1) from None
        typer.echo(str(png))
        return
    table = Table(title="mazes")
    for column in ("name", "cells", "metres", "free cells", "crossing steps", "about"):
        table.add_column(column, overflow="fold")
    shipped = set(maze_names())
    for spec, m in zip(specs, loaded, strict=True):
        rows, cols = m.grid.shape
        free = int((~m.grid).sum())
        table.add_row(
            m.name,
            f"{cols} x {rows}",
            f"{m.width:.1f} x {m.height:.1f}",
            f"{free} ({free / m.grid.size:.0%})",
            str(crossing_steps(m)),
            maze_note(spec) if spec in shipped else "",
        )
    rich_console().print(table)
