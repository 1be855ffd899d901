"""`colony demo`: the whole colony on one machine, through the interfaces a user has.

Starts `colony server` (embedded SQLite in the demo dir, local workers) as a subprocess,
evolves the paper's experiment over the REST API with a live progress bar, starts virtual
EvBots (`colony agent --emulate --tracker`: the BasicX emulator on a pty, the real serial path,
and an emulated overhead tracker publishing their poses), pushes
the run's best to them, lets them explore, then prints a colony summary and writes the plots.
Every child runs in its own session, so Ctrl-C reaches only this process, which stops the
robots first and the server (with its workers) last; nothing is left running.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Annotated, Any

import httpx
import typer
from rich.console import Console
from rich.table import Table

from colony.champion import held_out_cells, run_champion_lines
from colony.client import rich_console
from colony.robot_cli import robots_table, workers_table
from colony.run_cli import follow_run

STOP_TIMEOUT_S = 30.0
START_TIMEOUT_S = 120.0
POLL_S = 0.2


class DemoError(Exception):
    """A step of the demo failed; the message says which and where its log is."""


def free_ports(*preferred: int) -> list[int]:
    """Each of `preferred` if it is free on 127.0.0.1, else (or for 0) a free port the OS
    picks; all different: every socket is held until all are bound, named ports first, so the
    OS never hands out one port twice, nor one named after it."""
    with contextlib.ExitStack() as held:
        sockets = [held.enter_context(socket.socket()) for _ in preferred]
        for i in sorted(range(len(preferred)), key=lambda i: preferred[i] == 0):
            if not _bind(sockets[i], preferred[i]):
                raise DemoError("no free port on 127.0.0.1")
        return [int(s.getsockname()[1]) for s in sockets]


def _bind(s: socket.socket, wanted: int) -> bool:
    """Bind `s` to `wanted` on 127.0.0.1 if it is free (0: any), else to a port the OS picks."""
    for port in (wanted, 0) if wanted else (0,):
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            continue
        return True
    return False


def colony_argv() -> list[str]:
    """How to run this installation's `colony` command in a child process."""
    return [sys.executable, "-c", "from colony.cli import main; main()"]


@dataclass
class Children:
    """The demo's child processes; `stop` ends them newest first, each exactly once."""

    processes: list[tuple[str, subprocess.Popen[bytes], IO[bytes]]] = field(default_factory=list)

    def start(self, name: str, args: list[str], log: Path) -> subprocess.Popen[bytes]:
        out = log.open("wb")
        try:
            proc = subprocess.Popen(
                colony_argv() + args,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        except BaseException:
            out.close()
            raise
        self.processes.append((name, proc, out))
        return proc

    def stop(self, names: Callable[[str], bool] = lambda _: True) -> list[str]:
        """SIGINT the chosen children, wait, SIGKILL stragglers, reap, close their logs; the
        names of those stopped."""
        chosen = [p for p in reversed(self.processes) if names(p[0])]
        for _, proc, _ in chosen:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for _, proc, out in chosen:
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            out.close()
        self.processes = [p for p in self.processes if p not in chosen]
        return [name for name, _, _ in chosen]


def _plural(n: int, noun: str) -> str:
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _stopped(names: list[str], workers: int, then: str) -> str:
    """What `Children.stop` stopped, in words (its robots, then the server with its workers),
    and `then`."""
    robots = sum(name != "server" for name in names)
    parts = [_plural(robots, "robot")] if robots else []
    if "server" in names:
        parts.append(f"the server and its {_plural(workers, 'worker')}")
    return f"stopped {', then '.join(parts)}; {then}" if parts else then


def _sigterm(_signum: int, _frame: FrameType | None) -> None:
    raise KeyboardInterrupt


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """A `kill` of the demo cleans up like Ctrl-C does."""
    previous = signal.signal(signal.SIGTERM, _sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def wait_until(
    predicate: Callable[[], bool], timeout: float, what: str, alive: Callable[[], None]
) -> None:
    """Poll a condition no event announces (a REST view) until a deadline; `alive` raises
    when a child the condition depends on has died."""
    deadline = time.monotonic() + timeout
    tick = threading.Event()
    while not predicate():
        alive()
        if time.monotonic() > deadline:
            raise DemoError(f"timed out after {timeout:.0f} s waiting for {what}")
        tick.wait(POLL_S)


def _get(client: httpx.Client, path: str) -> Any:
    response = client.get(path)
    response.raise_for_status()
    return response.json()


def _healthy(client: httpx.Client) -> bool:
    try:
        return client.get("/healthz").status_code == 200
    except httpx.HTTPError:
        return False


def write_plots(client: httpx.Client, run: dict[str, Any], out: Path) -> list[Path]:
    """best.json, fitness.png, paths.png, network.png and responses.png from the REST API."""
    from evorobotics import plots
    from evorobotics.analysis import analyze
    from evorobotics.analysis_plots import responses_plot
    from evorobotics.document import ControllerDocument
    from evorobotics.evolution import GenerationSummary
    from schemas.run import RunConfig

    run_id = run["id"]
    config = RunConfig.model_validate(run["config"])
    history = [
        GenerationSummary(g["generation"], g["best"], g["mean"], g["worst"], g["nan_count"])
        for g in _get(client, f"/api/runs/{run_id}/generations")
    ]
    response = client.get(f"/api/runs/{run_id}/best")
    response.raise_for_status()
    best = ControllerDocument.from_json(response.content)
    files = [out / n for n in ("best.json", "fitness.png", "paths.png", "network.png")]
    files[0].write_text(best.to_json())
    plots.fitness_plot(history, files[1])
    plots.paths_plot(config, best, files[2])
    plots.network_plot(best.spec, best.weights, files[3])
    responses = out / "responses.png"
    responses_plot(analyze(best), responses)
    return [*files, responses]


def summary_tables(
    run: dict[str, Any], robots: list[dict[str, Any]], workers: list[Any]
) -> list[Table]:
    """The colony at the end: its robots, the workers and the run."""
    run_table = Table(title="run")
    for column in ("id", "status", "generations", "evaluations", "best training fitness"):
        run_table.add_column(column)
    for column in ("champion", "roaming nominal / gap", "stuck nominal / gap"):
        run_table.add_column(column)
    best = run.get("best_fitness_so_far")
    run_table.add_row(
        str(run["id"]),
        run["status"],
        f"{run['generation']}/{run['generations']}",
        str(run["evaluations"]),
        "-" if best is None else f"{best:.4f}",
        *held_out_cells(run.get("champion")),
    )
    return [robots_table(robots), workers_table(workers), run_table]


def demo_command(
    out: Annotated[Path, typer.Option("--dir", help="demo directory (database, logs, plots)")] = (
        Path("demo")
    ),
    robots: Annotated[int, typer.Option(min=0, max=64, help="virtual EvBots")] = 8,
    explore_seconds: Annotated[
        float, typer.Option(min=0.0, help="how long the robots explore")
    ] = 20.0,
    generations: Annotated[int | None, typer.Option(help="generations [350]")] = None,
    population: Annotated[int | None, typer.Option(help="individuals per generation [100]")] = None,
    seed: Annotated[int | None, typer.Option(help="run seed [0]")] = None,
    workers: Annotated[
        int, typer.Option(min=1, help="local worker processes (default: one per core)")
    ] = max(1, os.cpu_count() or 1),
    port: Annotated[int, typer.Option(help="HTTP port; taken or 0: a free one")] = 8000,
    zenoh_port: Annotated[int, typer.Option(help="zenoh port; taken or 0: a free one")] = 7447,
    keep_running: Annotated[
        bool, typer.Option("--keep-running", help="leave server and dashboard up until Ctrl-C")
    ] = False,
) -> None:
    """Evolve the paper's controller on a local colony, drive virtual EvBots with it, summarise."""
    console = rich_console()
    out = out.resolve()
    (out / "logs").mkdir(parents=True, exist_ok=True)
    children = Children()
    started = time.perf_counter()
    try:
        port, zenoh_port = free_ports(port, zenoh_port)
        with sigterm_as_interrupt():
            _demo(
                console,
                children,
                out,
                robots=robots,
                explore_seconds=explore_seconds,
                overrides={"generations": generations, "population": population, "seed": seed},
                workers=workers,
                port=port,
                zenoh_port=zenoh_port,
                keep_running=keep_running,
            )
    except KeyboardInterrupt:
        console.print("interrupted: stopping the colony")
        raise typer.Exit(130) from None
    except (DemoError, httpx.HTTPError) as exc:
        console.print(f"[red]colony demo: {exc}[/red]")
        raise typer.Exit(1) from None
    finally:
        took = time.perf_counter() - started
        then = f"nothing is left running; demo took {took:.1f} s (its files stay in {out})"
        console.print(_stopped(children.stop(), workers, then), highlight=False)


def _demo(
    console: Console,
    children: Children,
    out: Path,
    *,
    robots: int,
    explore_seconds: float,
    overrides: dict[str, int | None],
    workers: int,
    port: int,
    zenoh_port: int,
    keep_running: bool,
) -> None:
    from rich.progress import BarColumn, Progress, TimeElapsedColumn

    from colony.evolve import COMPILING
    from evorobotics.sim import kernel_cached
    from schemas.run import RunConfig

    logs = out / "logs"
    url = f"http://127.0.0.1:{port}"
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    server = children.start(
        "server",
        [
            "server",
            "--db",
            f"sqlite:///{out / 'colony.db'}",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--zenoh-listen",
            endpoint,
            "--workers",
            str(workers),
        ],
        logs / "server.log",
    )

    def alive() -> None:
        for name, proc, _ in children.processes:
            if proc.poll() is not None:
                raise DemoError(f"{name} exited with status {proc.returncode}: see {logs}/")

    t0 = time.perf_counter()
    with httpx.Client(base_url=url, timeout=60.0) as client:
        wait_until(lambda: _healthy(client), START_TIMEOUT_S, "the server", alive)
        console.print(f"server {url} (pid {server.pid}), {workers} local workers, zenoh {endpoint}")
        body = {k: v for k, v in overrides.items() if v is not None}
        response = client.post("/api/runs", json=body)
        if response.is_error:
            raise DemoError(f"POST /api/runs: {response.status_code} {response.text}")
        run = response.json()
        console.print(
            f"run {run['id']}: population {run['config']['population']}, "
            f"{run['generations']} generations (the paper's experiment unless overridden)"
        )
        if not kernel_cached(RunConfig.model_validate(run["config"]).network_spec):
            console.print(COMPILING)  # by the workers, which share this machine's cache
        run = follow_run(client, run["id"], console, alive)
        if run["status"] != "completed":
            raise DemoError(f"run {run['id']} {run['status']}: {run['error']}")
        console.print(f"evolved in {time.perf_counter() - t0:.1f} s", highlight=False)
        for line in run_champion_lines(run):
            console.print(line, highlight=False)

        ids = [f"evbot-{i + 1}" for i in range(robots)]
        for index, robot in enumerate(ids):
            children.start(
                robot,
                [
                    "agent",
                    "--emulate",
                    "--tracker",  # an overhead tracker's poses: calibration, stuck alarms
                    "--robot-id",
                    robot,
                    "--connect",
                    endpoint,
                    "--server",
                    url,
                    "--seed",
                    str(run["seed"]),
                    "--index",
                    str(index),
                    "--state-dir",
                    str(out / "agents" / robot),
                    "--log-level",
                    "WARNING",
                ],
                logs / f"{robot}.log",
            )

        def all_online() -> bool:
            online = {r["id"] for r in _get(client, "/api/robots") if r["online"]}
            return online >= set(ids)

        wait_until(all_online, START_TIMEOUT_S, f"{robots} robots online", alive)
        for robot in ids:
            push = client.post(f"/api/robots/{robot}/controller", json={"run_id": run["id"]})
            if push.is_error or not push.json()["accepted"]:
                raise DemoError(f"push to {robot} refused: {push.text}")
        console.print(f"pushed run {run['id']}'s champion to {robots} robots; exploring")
        with Progress(
            "exploring", BarColumn(), TimeElapsedColumn(), console=console, transient=True
        ) as bar:
            task = bar.add_task("explore", total=explore_seconds)
            end = time.monotonic() + explore_seconds
            tick = threading.Event()
            while (left := end - time.monotonic()) > 0:
                alive()
                tick.wait(min(0.5, left))
                bar.update(task, completed=explore_seconds - max(0.0, end - time.monotonic()))
        details = [_get(client, f"/api/robots/{robot}") for robot in ids]
        for table in summary_tables(run, details, _get(client, "/api/workers")):
            console.print(table)
        files = write_plots(client, run, out)
        console.print("wrote " + ", ".join(str(f) for f in files))
        if not keep_running:
            console.print(
                "the dashboard stops with the server; `colony demo --keep-running` keeps them up",
                highlight=False,
            )
            return
        up = (
            f"still running: the server and its {_plural(workers, 'worker')}, dashboard "
            f"{url}/ and metrics {url}/metrics, until Ctrl-C"
        )
        console.print(_stopped(children.stop(lambda name: name != "server"), workers, up))
        tick = threading.Event()
        try:
            while True:
                alive()
                tick.wait(1.0)
        except KeyboardInterrupt:  # the way this mode ends, not a failure
            return
