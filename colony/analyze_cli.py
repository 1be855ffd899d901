"""`colony analyze`: temporal responses of one controller (docs/analysis.md).

The controller comes from a document file, or from a server's REST API (docs/api.md):
`--server URL --run ID` (the run's best) or `--server URL --sha SHA256`. Prints a rich table or
`--json`; `--out DIR` also writes DIR/analysis.json and DIR/responses.png.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import httpx
import typer
from rich.console import Console
from rich.table import Table

from evorobotics.analysis import Analysis, analyze
from evorobotics.document import ControllerDocument
from evorobotics.errors import ControllerDocumentError

TIMEOUT_S = 30.0


def _fail(message: str) -> typer.Exit:
    typer.echo(f"colony analyze: {message}", err=True)
    return typer.Exit(code=2)


def fetch_document(
    server: str, *, run: int | None = None, sha: str | None = None
) -> ControllerDocument:
    """GET a run's best or a controller by sha256; ValueError with the server's reason."""
    if (run is None) == (sha is None):
        raise ValueError("give exactly one of run and sha")
    path = f"/api/runs/{run}/best" if run is not None else f"/api/controllers/{sha}"
    url = server.rstrip("/") + path
    try:
        response = httpx.get(url, timeout=TIMEOUT_S)
    except httpx.HTTPError as exc:
        raise ValueError(f"cannot reach {server}: {exc}") from None
    if response.is_error:
        raise ValueError(f"GET {url}: {response.status_code} {response.text}")
    try:
        return ControllerDocument.from_json(response.content)
    except ControllerDocumentError as exc:
        raise ValueError(f"GET {url}: {exc}") from None


def _load(
    controller: Path | None, server: str | None, run: int | None, sha: str | None
) -> ControllerDocument:
    if controller is not None:
        if server is not None or run is not None or sha is not None:
            raise _fail("give CONTROLLER or --server with --run/--sha, not both")
        try:
            return ControllerDocument.from_json(controller.read_bytes())
        except (OSError, ControllerDocumentError) as exc:
            raise _fail(f"{controller}: {exc}") from None
    if server is None or (run is None) == (sha is None):
        raise _fail("give a CONTROLLER file, or --server URL with exactly one of --run, --sha")
    try:
        return fetch_document(server, run=run, sha=sha)
    except ValueError as exc:
        raise _fail(str(exc)) from None


def _steps(value: int | None) -> str:
    return "no" if value is None else str(value)


def print_table(a: Analysis) -> None:
    """Baseline, settling per contact and duration, distinct responses and memory."""
    console = Console()
    period = f" (period {a.baseline.period})" if a.baseline.kind == "cycle" else ""
    console.print(
        f"controller {a.sha256[:12]}  baseline after {a.warmup} zero steps: "
        f"{a.baseline.kind}{period}  tol {a.settle_tol:g}, horizon {a.max_steps} steps"
    )
    table = Table(title="steps to settle after the last contact step (no = not within horizon)")
    table.add_column("contact")
    for d in sorted({c.duration for c in a.contacts}):
        table.add_column(f"held {d}", justify="right")
    table.add_column("peak |dev|", justify="right")
    for label in dict.fromkeys(c.label for c in a.contacts):
        row = [c for c in a.contacts if c.label == label]
        cells = []
        for c in row:
            cell = _steps(c.settle_steps)
            if c.settle_steps is None and c.new_steady_steps is not None:
                cell = f"new {c.new_steady_steps}"
            cells.append(cell)
        table.add_row(label, *cells, f"{max(c.peak_deviation for c in row):.3g}")
    console.print(table)
    distinct = Table(title=f"distinct motor responses (reactive bound {a.reactive_bound})")
    distinct.add_column("history k", justify="right")
    distinct.add_column("sequences", justify="right")
    distinct.add_column("distinct", justify="right")
    for k, n in enumerate(a.distinct, start=1):
        distinct.add_row(str(k), str(a.reactive_bound**k), str(n))
    console.print(distinct)
    more = " (or more: raise --history)" if a.memory_saturated else ""
    console.print(
        f"longest settle after a one-step single contact: {_steps(a.max_settle)}; "
        f"effective memory {a.memory} step(s){more}"
    )


def analyze_command(
    controller: Annotated[
        Path | None, typer.Argument(help="controller document JSON (e.g. out/best.json)")
    ] = None,
    server: Annotated[str | None, typer.Option(help="server base URL")] = None,
    run: Annotated[int | None, typer.Option(help="analyze this run's best (with --server)")] = None,
    sha: Annotated[
        str | None, typer.Option(help="analyze the controller with this sha256 (with --server)")
    ] = None,
    history: Annotated[int, typer.Option(help="longest whisker history k")] = 3,
    settle_tol: Annotated[float, typer.Option(help="motor command tolerance")] = 1e-3,
    max_steps: Annotated[int, typer.Option(help="settling horizon in steps")] = 50,
    as_json: Annotated[bool, typer.Option("--json", help="print the analysis as JSON")] = False,
    out: Annotated[
        Path | None, typer.Option(help="write analysis.json and responses.png here")
    ] = None,
) -> None:
    """Settling times after whisker contacts and distinct responses to whisker histories."""
    doc = _load(controller, server, run, sha)
    try:
        result = analyze(doc, history=history, settle_tol=settle_tol, max_steps=max_steps)
    except ValueError as exc:
        raise _fail(str(exc)) from None
    text = json.dumps(result.to_dict(), allow_nan=False)
    if as_json:
        typer.echo(text)
    else:
        print_table(result)
    if out is not None:
        from evorobotics.analysis_plots import responses_plot  # matplotlib: only when writing

        out.mkdir(parents=True, exist_ok=True)
        (out / "analysis.json").write_text(text + "\n")
        responses_plot(result, out / "responses.png")
        if not as_json:
            typer.echo(f"wrote {out / 'analysis.json'}, {out / 'responses.png'}")
