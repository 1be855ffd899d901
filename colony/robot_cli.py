"""`colony status`, `colony workers`, `colony robots` and `colony robot ...`: the colony's
state and one robot's commands over the REST API."""

from __future__ import annotations

import itertools
from datetime import UTC, datetime
from typing import Annotated, Any

import httpx
import typer
from rich.table import Table

from colony.client import (
    DEFAULT_SERVER,
    SHORT_SHA,
    JsonOpt,
    ServerOpt,
    TokenOpt,
    call_server,
    cell,
    checked,
    open_client,
    print_json,
    rich_console,
)
from colony.run_cli import runs_table


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
        print_json(colony)
        return
    console = rich_console()
    counts = ", ".join(f"{k} {v}" for k, v in sorted(colony["runs"].items())) or "none"
    jobs = colony["jobs"]
    console.print(f"runs: {counts}")
    console.print(
        f"jobs of the generations in flight: pending {jobs['pending']}, leased {jobs['leased']}, "
        f"done {jobs['done']}"
    )
    console.print(runs_table(colony["active"], "active runs"))
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
        print_json(workers)
    else:
        rich_console().print(workers_table(workers))


def robots_command(
    ctx: typer.Context,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Every robot ever seen: online, state, steps, controller, replacement policy."""
    robots = call_server(ctx, server, token, "GET", "/api/robots")
    if as_json:
        print_json(robots)
    else:
        rich_console().print(robots_table(robots))


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
        print_json(detail)
        return
    for key in (
        "id", "online", "state", "steps", "stuck_events", "whiskers", "controller_sha256",
        "controller_run", "controller_rank", "controller_generation", "boot",
    ):  # fmt: skip
        typer.echo(f"{key:22s} {cell(detail[key])}")
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
        print_json(detail)
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
        print_json(ledger)
        return
    table = Table(title=f"stuck events of {robot}")
    for column in ("step", "reason", "controller", "policy", "replacement", "steps run"):
        table.add_column(column)
    for e in ledger["events"]:
        table.add_row(
            cell(e["step"]),
            e["reason"],
            (e["controller_sha256"] or "-")[:SHORT_SHA],
            cell(e["policy"]),
            (e["replacement_sha256"] or "-")[:SHORT_SHA],
            cell(e["steps_run"]),
        )
    rich_console().print(table)
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
    rich_console().print(runs)


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
        when = None if since is None else datetime.fromisoformat(since)
    except ValueError:
        raise typer.BadParameter(f"--since {since!r} is not an ISO 8601 time") from None
    if when is not None and when.tzinfo is None:  # the traces' times are UTC, as the API's
        when = when.replace(tzinfo=UTC)
    start = None if when is None else when.timestamp()
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
    c = stored["calibration"]
    if as_json:  # the fit's members at the top, with whose it is and when it was stored
        print_json({"robot": stored["robot"], "stored_at": stored["stored_at"], **c})
        return
    table = Table(title=f"calibration of {robot} from {c['samples']} samples")
    for column in ("", "left", "", "centre", "", "right"):
        table.add_column(column, justify="right")
    ranges = [f"{1000 * r:.1f}" for r in c["whisker_range"]]
    errs = [f"+-{1000 * e:.1f}" for e in c["uncertainty"]["whisker_range"]]
    table.add_row("whisker range, mm", *ranges)
    table.add_row("uncertainty, mm", *errs)
    rich_console().print(table)
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
        print_json(result)
    elif result["accepted"]:
        typer.echo(f"robot {result['robot']} runs {cell(result['sha256'])}")
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


def robot_forget(
    ctx: typer.Context,
    robot: str,
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
) -> None:
    """Forget a stale robot: its entry, last report, stuck events and traces (stop its agent
    first; the controllers' field statistics stay)."""
    try:
        with open_client(ctx, server, token) as client:
            response = client.delete(f"/api/robots/{robot}")
    except httpx.HTTPError as exc:
        typer.echo(f"error: cannot reach {server}: {exc}", err=True)
        raise typer.Exit(1) from exc
    checked(response, server)
    typer.echo(f"robot {robot} forgotten")


robot_app.command("forget")(robot_forget)
