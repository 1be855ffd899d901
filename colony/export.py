"""Files of a study or a run for analysis elsewhere: tables as CSV and Parquet, figures as PNG.

The inputs are the REST API's JSON (docs/api.md, docs/studies.md) as plain dicts, so the same
writers serve `colony study export` and `colony run export`. Every table is written twice with
the same columns and values: CSV (the csv module; floats as repr, so they parse back to the
same bits; an empty field is a missing value) and Parquet (pyarrow, typed columns, nulls).
Pyarrow and matplotlib are imported only when a file is written: they are slow to import.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

Kind = Literal["str", "int", "float"]
Row = Mapping[str, Any]
Fetch = Callable[[str], Any]
"""GET a REST path and return its JSON (the caller owns the connection and its errors)."""

METRIC_ORDER = (
    "best_fitness",
    "validation_score",
    "roaming",
    "stuck",
    "max_offset",
    "coverage",
    "gap_roaming",
    "gap_stuck",
)
"""The final metrics of a completed run (docs/studies.md), in the order tables and plots use."""

COMPONENTS = ("curve_length", "net_offset", "max_offset", "stuck")
"""Eq 12's terms, in the order of an individual's per-trial `components`."""


@dataclass(frozen=True)
class Table:
    """Rows under typed columns; a missing key or None is a null."""

    name: str
    columns: tuple[tuple[str, Kind], ...]
    rows: tuple[Row, ...]


RUN_KEYS: tuple[tuple[str, Kind], ...] = (
    ("study", "str"),
    ("condition", "str"),
    ("seed", "int"),
    ("run_id", "int"),
)
"""Which run a row belongs to; the study and condition are null for a run outside a study."""

GENERATION_COLUMNS = (
    *RUN_KEYS,
    ("generation", "int"),
    ("best", "float"),
    ("mean", "float"),
    ("worst", "float"),
    ("nan_count", "int"),
)
INDIVIDUAL_COLUMNS = (
    *RUN_KEYS,
    ("generation", "int"),
    ("rank", "int"),
    ("index", "int"),
    ("parent", "int"),
    ("fitness", "float"),
    *((c, "float") for c in COMPONENTS),
    ("sha256", "str"),
)
CHAMPION_COLUMNS = (
    *RUN_KEYS,
    ("status", "str"),
    ("sha256", "str"),
    *((m, "float") for m in METRIC_ORDER),
)
SUMMARY_COLUMNS: tuple[tuple[str, Kind], ...] = (
    ("condition", "str"),
    ("metric", "str"),
    ("n", "int"),
    ("median", "float"),
    ("q1", "float"),
    ("q3", "float"),
    ("ci_low", "float"),
    ("ci_high", "float"),
)
COMPARISON_COLUMNS: tuple[tuple[str, Kind], ...] = (
    ("a", "str"),
    ("b", "str"),
    ("metric", "str"),
    ("u", "float"),
    ("p_value", "float"),
    ("p_holm", "float"),
    ("a12", "float"),
)


def run_key(run: Row, study: str | None) -> dict[str, Any]:
    """The RUN_KEYS of a StudyRun or a RunOut (`id` or `run_id`)."""
    return {
        "study": study,
        "condition": run.get("condition"),
        "seed": run["seed"],
        "run_id": run["run_id"] if "run_id" in run else run["id"],
    }


def generation_rows(key: Row, generations: Iterable[Row]) -> list[dict[str, Any]]:
    """GET /api/runs/{id}/generations under the run's key."""
    return [{**key, **g} for g in generations]


def individual_rows(key: Row, individuals: Row) -> list[dict[str, Any]]:
    """GET /api/runs/{id}/individuals under the run's key; each Eq 12 term is its mean over
    the trials."""
    rows = []
    for ind in individuals["individuals"]:
        trials = ind["components"]
        means = {
            c: math.fsum(t[i] for t in trials) / len(trials) if trials else None
            for i, c in enumerate(COMPONENTS)
        }
        rows.append(
            {
                **key,
                "generation": individuals["generation"],
                **{k: ind[k] for k in ("rank", "index", "parent", "fitness", "sha256")},
                **means,
            }
        )
    return rows


def _csv_cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


def write_table(out: Path, table: Table) -> list[Path]:
    """NAME.csv and NAME.parquet in `out`; the paths written."""
    names = [c for c, _ in table.columns]
    csv_path = out / f"{table.name}.csv"
    with csv_path.open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(names)
        for row in table.rows:
            writer.writerow([_csv_cell(row.get(c)) for c in names])
    import pyarrow as pa  # slow to import: only when writing
    import pyarrow.parquet as pq

    arrow = {"str": pa.string(), "int": pa.int64(), "float": pa.float64()}
    schema = pa.schema([(c, arrow[k]) for c, k in table.columns])
    arrays = {c: [_arrow_value(row.get(c), k) for row in table.rows] for c, k in table.columns}
    parquet_path = out / f"{table.name}.parquet"
    pq.write_table(pa.Table.from_pydict(arrays, schema=schema), parquet_path)
    return [csv_path, parquet_path]


def _arrow_value(value: Any, kind: Kind) -> Any:
    if value is None:
        return None
    return {"str": str, "int": int, "float": float}[kind](value)


def read_csv_table(path: Path, columns: Sequence[tuple[str, Kind]]) -> list[dict[str, Any]]:
    """A CSV written by `write_table` back as typed rows (None for an empty field)."""
    kinds = dict(columns)
    with path.open(newline="") as f:
        return [
            {c: None if v == "" else _arrow_value(v, kinds[c]) for c, v in row.items()}
            for row in csv.DictReader(f)
        ]


# ------------------------------------------------------------------------------------ studies


def study_tables(study: Row, fetch: Fetch) -> list[Table]:
    """Every table of a StudyOut: its runs' generations and final individuals (fetched), the
    completed runs' champions and metrics, the summary and the comparisons."""
    name = study["name"]
    generations: list[dict[str, Any]] = []
    individuals: list[dict[str, Any]] = []
    champions: list[dict[str, Any]] = []
    for run in study["runs"]:
        key = run_key(run, name)
        rid = run["run_id"]
        history = fetch(f"/api/runs/{rid}/generations")
        generations += generation_rows(key, history)
        if history:
            individuals += individual_rows(key, fetch(f"/api/runs/{rid}/individuals"))
        if run["status"] == "completed":
            best = fetch(f"/api/runs/{rid}/best")
            champions.append(
                {**key, "status": run["status"], "sha256": best["sha256"], **run["metrics"]}
            )
    summary = [
        {"condition": s["condition"], "metric": metric, **figures}
        for s in study["summary"]
        for metric, figures in s["final"].items()
    ]
    return [
        Table("generations", GENERATION_COLUMNS, tuple(generations)),
        Table("individuals", INDIVIDUAL_COLUMNS, tuple(individuals)),
        Table("champions", CHAMPION_COLUMNS, tuple(champions)),
        Table("summary", SUMMARY_COLUMNS, tuple(summary)),
        Table("comparisons", COMPARISON_COLUMNS, tuple(study["comparisons"])),
    ]


def export_study(study: Row, fetch: Fetch, out: Path) -> list[Path]:
    """The study's tables (CSV and Parquet), fitness.png and metrics.png in `out` (created);
    the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for table in study_tables(study, fetch):
        written += write_table(out, table)
    fitness_plot(study["summary"], out / "fitness.png")
    metrics_plot(study["runs"], [s["condition"] for s in study["summary"]], out / "metrics.png")
    return [*written, out / "fitness.png", out / "metrics.png"]


def export_run(
    run: Row, study: str | None, fetch: Fetch, out: Path, best: bytes | None
) -> list[Path]:
    """A RunOut's generations and latest generation's individuals (CSV and Parquet) in `out`
    (created), beside `config.json` and `best.json` (the document `best`, if the run has one)
    as `colony evolve --out` writes them, so `colony evolve --config config.json` reruns it;
    `study` names its study, if any. The paths written."""
    from schemas.run import RunConfig

    out.mkdir(parents=True, exist_ok=True)
    key = run_key(run, study)
    history = fetch(f"/api/runs/{run['id']}/generations")
    individuals = (
        individual_rows(key, fetch(f"/api/runs/{run['id']}/individuals")) if history else []
    )
    config = out / "config.json"
    config.write_text(RunConfig.model_validate(run["config"]).model_dump_json(indent=2) + "\n")
    written = [config]
    if best is not None:
        written.append(out / "best.json")
        written[-1].write_bytes(best)
    return [
        *written,
        *write_table(
            out, Table("generations", GENERATION_COLUMNS, tuple(generation_rows(key, history)))
        ),
        *write_table(out, Table("individuals", INDIVIDUAL_COLUMNS, tuple(individuals))),
    ]


# ------------------------------------------------------------------------------------ figures

PNG_METADATA: dict[str, Any] = {"Software": None}
"""No matplotlib version stamp: a PNG depends on its data only."""


def _pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt: Any, fig: Any, path: Path) -> None:
    fig.savefig(path, dpi=110, metadata=PNG_METADATA)
    plt.close(fig)


def fitness_plot(summary: Sequence[Row], path: Path) -> None:
    """Per condition, the median best of generation (training fitness) over generations with
    its 95 % CI band (over the condition's runs that reached each generation); the legend
    beside the axes, never over a band."""
    plt = _pyplot()

    fig, ax = plt.subplots(figsize=(8, 4))
    for s in summary:
        rows = s["generations"]
        if not rows:
            continue
        gens = [r["generation"] for r in rows]
        (line,) = ax.plot(gens, [r["best"]["median"] for r in rows], label=s["condition"])
        ax.fill_between(
            gens,
            [r["best"]["ci_low"] for r in rows],
            [r["best"]["ci_high"] for r in rows],
            color=line.get_color(),
            alpha=0.2,
            linewidth=0,
        )
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_xlabel("generation")
    ax.set_ylabel("best of generation (training fitness)\nmedian and 95 % CI")
    ax.set_title("training fitness per condition")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    else:
        ax.text(0.5, 0.5, "no generation yet", ha="center", va="center", transform=ax.transAxes)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(plt, fig, path)


def metrics_plot(runs: Sequence[Row], conditions: Sequence[str], path: Path) -> None:
    """One panel per final metric: a box plot of the completed runs' values per condition, each
    run a dot over it."""
    plt = _pyplot()

    values = {
        m: [
            [
                float(r["metrics"][m])
                for r in runs
                if r["condition"] == c
                and r["status"] == "completed"
                and r["metrics"].get(m) is not None
            ]
            for c in conditions
        ]
        for m in METRIC_ORDER
    }
    shown = [m for m in METRIC_ORDER if any(values[m])]
    cols = min(3, max(1, len(shown)))
    rows = max(1, math.ceil(len(shown) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.2 * rows), squeeze=False)
    flat = list(axes.flat)
    for ax, metric in zip(flat, shown, strict=False):
        ax.boxplot(values[metric], tick_labels=list(conditions))
        for i, sample in enumerate(values[metric], start=1):  # few seeds: show every run
            ax.plot([i] * len(sample), sample, "o", color="tab:blue", alpha=0.5, markersize=4)
        ax.set_title(metric)
        ax.set_xlabel("condition")
        ax.set_ylabel(metric)
        ax.tick_params(axis="x", labelrotation=20)
        ax.grid(alpha=0.3, axis="y")
    if not shown:
        flat[0].text(0.5, 0.5, "no completed run yet", ha="center", va="center")
        flat[0].set_axis_off()
    for ax in flat[len(shown) :]:
        ax.set_axis_off()
    fig.suptitle("final metrics of the completed runs")
    fig.tight_layout()
    _save(plt, fig, path)
