"""`colony evaluate`: does a controller explore? Its exploration report (docs/explore.md).

The controller comes from a document file, or from a server's REST API (docs/api.md):
`--server URL --run ID` (the run's best) or `--server URL --sha SHA256`. It runs in the
document's `world` when the document has one (a run's champion), else in the default World.
Prints a rich table or `--json`; bad input is one line `colony evaluate: ...` and exit code 2.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

if TYPE_CHECKING:
    from evorobotics.document import ControllerDocument
    from evorobotics.explore import Exploration
    from evorobotics.robustness import RobustnessMap
    from schemas.world import World


def _fail(message: str) -> typer.Exit:
    typer.echo(f"colony evaluate: {message}", err=True)
    return typer.Exit(code=2)


def report_dict(doc: ControllerDocument, e: Exploration, world: str) -> dict[str, Any]:
    """The JSON of `colony evaluate --json`: units in the keys, the document's own scores beside."""
    from evorobotics.explore import COVERAGE_CELL

    return {
        "controller": doc.sha256,
        "world": world,
        "maze": e.maze,
        "poses": e.poses,
        "steps": e.steps,
        "seed": e.seed,
        "reality_gap": e.reality_gap,
        "stuck_fraction_by_step": {str(h): v for h, v in e.stuck.items()},
        "confined_fraction": e.confined,
        "roaming_fraction": e.roaming,
        "mean_max_offset_m_by_step": {str(h): v for h, v in e.max_offset.items()},
        "mean_coverage_cells": e.coverage,
        "coverage_cell_m": COVERAGE_CELL,
        "mean_fitness_40_steps": e.fitness_40,
        "training_fitness": doc.fitness,
        "validation": None if doc.validation is None else doc.validation.model_dump(mode="json"),
    }


def _percent(x: float) -> str:
    return f"{100.0 * x:.1f} %"


def print_table(doc: ControllerDocument, e: Exploration, world: str) -> None:
    """One row per measure, then the document's training fitness and validation, labelled."""
    from rich.table import Table

    from colony.client import rich_console
    from evorobotics.explore import COVERAGE_CELL, PAPER_TRIAL

    console = rich_console()
    gap = ", reality gap" if e.reality_gap else ""
    console.print(
        f"controller {doc.sha256[:12]} in maze {e.maze!r}, {_world_label(world)}{gap}: {e.poses} unseen start "
        f"poses (exploration stream, seed {e.seed}) x {e.steps} steps"
    )
    table = Table(title="exploration report")
    table.add_column("measure")
    table.add_column("value", justify="right")
    for h, fraction in e.stuck.items():
        table.add_row(f"stuck by step {h}", _percent(fraction))
    table.add_row(f"confined (before sticking, over {e.steps} steps)", _percent(e.confined))
    table.add_row(f"roaming (neither stuck nor confined, {e.steps} steps)", _percent(e.roaming))
    for h, metres in e.max_offset.items():
        table.add_row(f"mean max offset by step {h}", f"{metres:.3f} m")
    table.add_row(f"mean coverage ({COVERAGE_CELL:g} m cells)", f"{e.coverage:.1f} cells")
    table.add_row(f"mean Eq 12 fitness, first {PAPER_TRIAL} steps", f"{e.fitness_40:.3f}")
    console.print(table)
    trained = "none" if doc.fitness is None else f"{doc.fitness:.3f}"
    console.print(f"training fitness (mean Eq 12 over its run's training trials): {trained}")
    v = doc.validation
    if v is None:
        console.print("validation: none (not a run's validated champion)")
    else:
        console.print(
            f"validation ({v.poses} poses x {v.steps} steps, run seed {v.seed}, "
            f"{v.candidates} candidates, training rank {v.training_rank}): score {v.score:.3f}, "
            f"stuck {_percent(v.stuck)}, roaming {_percent(v.roaming)}"
        )


def _world_label(world: str) -> str:
    if world.startswith("robot:"):
        return f"robot {world[6:]}'s calibrated world"
    return "the document's world" if world == "document" else "the default World"


def print_map(doc: ControllerDocument, m: RobustnessMap, world: str) -> None:
    """Two tables, roaming then stuck: a row per whisker range, a column per gain ratio."""
    from rich.table import Table

    from colony.client import rich_console

    console = rich_console()
    console.print(
        f"controller {doc.sha256[:12]} in maze {m.maze!r}, {_world_label(world)}: {m.poses} unseen start "
        f"poses (robustness stream, seed {m.seed}) x {m.steps} steps in every cell"
    )
    for name in ("roaming", "stuck"):
        table = Table(
            title=f"{name}, % of trials", caption="columns: wheel gain ratio, left / right"
        )
        table.add_column("whisker")
        for ratio in m.gain_ratios:
            table.add_column(f"{ratio:g}", justify="right")
        for r, row in zip(m.whisker_ranges, getattr(m, name), strict=True):
            table.add_row(f"{1000 * r:g} mm", *(f"{100 * v:.0f}" for v in row))
        console.print(table)
    console.print(f"worst cell's roaming: {_percent(m.worst_roaming)}")


def _robustness(
    doc: ControllerDocument,
    world: tuple[str, World | None],
    poses: int,
    steps: int,
    maze: str,
    seed: int,
    out: Path,
    as_json: bool,
    threads: int,
) -> None:
    """`--robustness`: the map, printed or as JSON, and its heat map in OUT/robustness.png."""
    from evorobotics.errors import EvoError
    from evorobotics.plots import robustness_plot
    from evorobotics.robustness import robustness

    try:
        m = robustness(
            doc.spec,
            doc.weights,
            poses=poses,
            steps=steps,
            maze=maze,
            seed=seed,
            world=world[1],
            threads=threads,
        )
    except (EvoError, ValueError) as exc:
        raise _fail(str(exc)) from None
    try:
        out.mkdir(parents=True, exist_ok=True)
        robustness_plot(m, out / "robustness.png")
    except OSError as exc:
        raise _fail(f"--out: {exc}") from None
    if as_json:
        typer.echo(json.dumps({"controller": doc.sha256, **m.as_dict()}, allow_nan=False))
    else:
        print_map(doc, m, world[0])
        typer.echo(f"wrote {out / 'robustness.png'}")


def evaluate_command(
    controller: Annotated[
        Path | None, typer.Argument(help="controller document JSON (e.g. out/best.json)")
    ] = None,
    server: Annotated[str | None, typer.Option(help="server base URL")] = None,
    run: Annotated[
        int | None, typer.Option(help="evaluate this run's best (with --server)")
    ] = None,
    sha: Annotated[
        str | None,
        typer.Option(
            help="evaluate the controller with this sha256 or 8+ digit prefix (with --server)"
        ),
    ] = None,
    robot: Annotated[
        str | None,
        typer.Option(
            help="in this robot's calibrated world (with --server; colony robot calibrate)"
        ),
    ] = None,
    poses: Annotated[
        int | None,
        typer.Option(help="unseen start poses, one trial each (per cell with --robustness)"),
    ] = None,
    steps: Annotated[int, typer.Option(help="steps of each trial (H)")] = 1000,
    maze: Annotated[str, typer.Option(help="shipped maze, gen:SIZE:SEED or a file")] = "paper",
    seed: Annotated[int, typer.Option(help="seed of the exploration start poses")] = 0,
    reality_gap: Annotated[
        bool, typer.Option("--reality-gap", help="draw whisker ranges and motor gains per trial")
    ] = False,
    robustness: Annotated[
        bool,
        typer.Option(
            "--robustness",
            help="map roaming and stuck over whisker range x wheel gain ratio instead "
            "(default 50 poses per cell)",
        ),
    ] = False,
    out: Annotated[
        Path, typer.Option(help="with --robustness: directory of robustness.png (created)")
    ] = Path("out"),
    as_json: Annotated[bool, typer.Option("--json", help="print the report as JSON")] = False,
    threads: Annotated[
        int | None,
        typer.Option(help="simulation threads; the report is the same [cores available]"),
    ] = None,
) -> None:
    """Stuck, confined and roaming fractions, offsets, coverage and Eq 12 fitness over long runs,
    or (`--robustness`) the same trials across the reality gap, cell by cell.

    Trials start from poses no training or validation trial uses (docs/explore.md).
    """
    if threads is not None and threads < 1:
        raise _fail(f"--threads must be >= 1, got {threads}")
    # numpy's OpenBLAS would start a thread per core, each spinning about 0.1 s of CPU as it
    # loads: a report uses no BLAS worth a thread
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    # numba and the simulator: only when evaluating, so `colony --help` stays fast
    from colony.documents import load_document, robot_world
    from evorobotics.errors import EvoError
    from evorobotics.evaluate import available_cores
    from evorobotics.explore import MAX_ROBOT_STEPS, explore
    from evorobotics.maze import load_maze

    if poses is None:
        poses = 50 if robustness else 1000
    if poses < 1 or steps < 1:
        raise _fail(f"--poses and --steps must be >= 1, got {poses} and {steps}")
    if robustness and reality_gap:
        raise _fail("--robustness sets the gap per cell: leave out --reality-gap")
    if not robustness and poses * steps > MAX_ROBOT_STEPS:
        raise _fail(f"--poses x --steps = {poses * steps} exceeds {MAX_ROBOT_STEPS} robot steps")
    if seed < 0:
        raise _fail(f"--seed must be >= 0, got {seed}")
    try:
        if robot is not None and server is None:
            raise ValueError("--robot needs --server: the calibration is stored there")
        doc = load_document(  # with --robot, --server is where the calibration is
            controller, None if robot is not None and controller is not None else server, run, sha
        )
        world: tuple[str, World | None] = (
            ("document" if doc.world is not None else "default", doc.world)
            if robot is None or server is None
            else (f"robot:{robot}", robot_world(server, robot, doc.world))
        )
    except ValueError as exc:
        raise _fail(str(exc)) from None
    try:
        load_maze(maze)
    except (EvoError, OSError, ValueError) as exc:
        raise _fail(f"--maze: {exc}") from None
    workers = available_cores() if threads is None else threads
    if robustness:
        _robustness(doc, world, poses, steps, maze, seed, out, as_json, workers)
        return
    try:
        result = explore(
            doc.spec,
            doc.weights,
            poses=poses,
            steps=steps,
            maze=maze,
            seed=seed,
            reality_gap=reality_gap,
            world=world[1],
            threads=workers,
        )
    except (EvoError, ValueError) as exc:
        raise _fail(str(exc)) from None
    if as_json:
        typer.echo(json.dumps(report_dict(doc, result, world[0]), allow_nan=False))
    else:
        print_table(doc, result, world[0])
