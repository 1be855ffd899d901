"""`colony analyze`: temporal responses of one controller (docs/analysis.md).

The controller comes from a document file, or from a server's REST API (docs/api.md):
`--server URL --run ID` (the run's best) or `--server URL --sha SHA256`. Prints a rich table or
`--json`; `--out DIR` also writes DIR/analysis.json, responses.png, network.png (Fig 5 before
and after training) and encounter.png (Fig 7 close-up, in `--maze`, the paper maze by default).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from evorobotics.thresholds import RESOLUTION_MM, TOLERANCE_MM

if TYPE_CHECKING:
    from evorobotics.analysis import Analysis
    from evorobotics.document import ControllerDocument


def _fail(message: str) -> typer.Exit:
    typer.echo(f"colony analyze: {message}", err=True)
    return typer.Exit(code=2)


def _steps(value: int | None) -> str:
    return "no" if value is None else str(value)


def print_table(a: Analysis) -> None:
    """Baseline, settling per contact and duration, distinct responses and memory."""
    from rich.table import Table

    from colony.client import rich_console

    console = rich_console()
    period = f" (period {a.baseline.period})" if a.baseline.kind == "cycle" else ""
    console.print(
        f"controller {a.sha256[:12]}  baseline after {a.warmup} zero steps: "
        f"{a.baseline.kind}{period}  tolerance {a.tolerance_mm_per_step:g} mm per step "
        f"(command 1 = {a.full_speed_mm_per_step:g} mm per step), horizon {a.max_steps} steps"
    )
    table = Table(title="steps to settle after the last contact step (no = not within horizon)")
    table.add_column("contact")
    for d in sorted({c.duration for c in a.contacts}):
        table.add_column(f"held {d}", justify="right")
    table.add_column("peak |dev| mm/step", justify="right")
    for label in dict.fromkeys(c.label for c in a.contacts):
        row = [c for c in a.contacts if c.label == label]
        cells = []
        for c in row:
            cell = _steps(c.settle_steps)
            if c.settle_steps is None and c.new_steady_steps is not None:
                cell = f"new {c.new_steady_steps}"
            cells.append(cell)
        table.add_row(label, *cells, f"{max(c.peak_deviation_mm_per_step for c in row):.3g}")
    console.print(table)
    distinct = Table(
        title=f"distinct motor responses in cells of {a.resolution_mm_per_step:g} mm per step "
        f"(reactive bound {a.reactive_bound})"
    )
    distinct.add_column("history k", justify="right")
    distinct.add_column("sequences", justify="right")
    distinct.add_column("distinct", justify="right")
    for k, n in enumerate(a.distinct, start=1):
        distinct.add_row(str(k), str(a.reactive_bound**k), str(n))
    console.print(distinct)
    more = " (or more: raise --history)" if a.memory_saturated else ""
    console.print(
        f"longest settle after a one-step single contact: {_steps(a.max_settle_steps)}; "
        f"effective memory {a.memory} step(s){more}"
    )


def analyze_command(
    controller: Annotated[
        Path | None, typer.Argument(help="controller document JSON (e.g. out/best.json)")
    ] = None,
    server: Annotated[str | None, typer.Option(help="server base URL")] = None,
    run: Annotated[int | None, typer.Option(help="analyze this run's best (with --server)")] = None,
    sha: Annotated[
        str | None,
        typer.Option(
            help="analyze the controller with this sha256 or 8+ digit prefix (with --server)"
        ),
    ] = None,
    history: Annotated[int, typer.Option(help="longest whisker history k")] = 3,
    tolerance_mm: Annotated[
        float,
        typer.Option(help="settled = within this wheel travel of the baseline, mm per step"),
    ] = TOLERANCE_MM,
    resolution_mm: Annotated[
        float, typer.Option(help="count distinct responses in cells this size, mm per step")
    ] = RESOLUTION_MM,
    max_steps: Annotated[int, typer.Option(help="settling horizon in steps")] = 50,
    as_json: Annotated[bool, typer.Option("--json", help="print the analysis as JSON")] = False,
    out: Annotated[
        Path | None,
        typer.Option(help="write analysis.json, responses.png, network.png, encounter.png here"),
    ] = None,
    maze: Annotated[
        str, typer.Option(help="maze of the encounter.png close-up (with --out)")
    ] = "paper",
    seed: Annotated[
        int | None,
        typer.Option(
            min=0,
            max=2**63 - 1,
            help="seed of network.png's generation-0 controller and encounter.png's start "
            "poses (default: the document's run seed, else 0)",
        ),
    ] = None,
) -> None:
    """Settling times after whisker contacts and distinct responses to whisker histories.

    Tolerances are wheel travel in mm per control step (command 1 = max_speed * dt = 30 mm per
    step in the default world). With --out, also the paper's Fig 5 before and after training
    and a Fig 7 close-up of one wall encounter (in the paper maze unless --maze).
    """
    # numba and the simulator: only when analysing, so `colony --help` stays fast
    from colony.documents import load_document
    from evorobotics.analysis import analyze
    from evorobotics.errors import EvoError
    from evorobotics.maze import load_maze

    try:
        doc = load_document(controller, server, run, sha)
    except ValueError as exc:
        raise _fail(str(exc)) from None
    if out is not None:
        try:
            load_maze(maze)
        except (EvoError, OSError) as exc:
            raise _fail(f"--maze: {exc}") from None
    try:
        result = analyze(
            doc,
            history=history,
            tolerance_mm=tolerance_mm,
            resolution_mm=resolution_mm,
            max_steps=max_steps,
        )
    except ValueError as exc:
        raise _fail(str(exc)) from None
    text = json.dumps(result.to_dict(), allow_nan=False)
    if as_json:
        typer.echo(text)
    else:
        print_table(result)
    if out is not None:
        _write_figures(doc, result, text, out, maze, _seed(doc, seed), quiet=as_json)


def _seed(doc: ControllerDocument, seed: int | None) -> int:
    """--seed, else the run seed in the document's provenance, else 0."""
    if seed is not None:
        return seed
    value = doc.provenance.get("seed") if isinstance(doc.provenance, dict) else None
    return value if isinstance(value, int) and value >= 0 else 0


def _write_figures(
    doc: ControllerDocument,
    result: Analysis,
    text: str,
    out: Path,
    maze: str,
    seed: int,
    *,
    quiet: bool,
) -> None:
    # matplotlib and the simulator: only when writing
    from evorobotics import analysis_plots as ap
    from evorobotics.errors import EvoError

    out.mkdir(parents=True, exist_ok=True)
    written = [out / n for n in ("analysis.json", "responses.png", "network.png")]
    written[0].write_text(text + "\n")
    ap.responses_plot(result, written[1])
    ap.network_before_after_plot(doc, seed, written[2])
    try:
        ap.encounter_plot(doc, out / "encounter.png", maze=maze, seed=seed)
        written.append(out / "encounter.png")
    except (ValueError, EvoError) as exc:  # never touches a wall; no room in the maze
        typer.echo(f"colony analyze: no encounter.png: {exc}", err=True)
    if not quiet:
        typer.echo("wrote " + ", ".join(str(p) for p in written))
