"""`colony evolve`: a whole evolutionary experiment in one process, with its files and plots.

Flags override a `--config` RunConfig JSON, which overrides the paper's defaults. A maze or
network given as a FILE is read here and shipped inside the config (maze text, NetworkSpec),
so `config.json` alone reproduces the run anywhere.
"""

from __future__ import annotations

import csv
import gc
import json
import math
import multiprocessing
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from colony.champion import champion_lines, training_progress
from colony.options import NominalOpt
from colony.run_inputs import (
    ConfigError,
    maze_value,
    name_maze_file,
    network_value,
    validation_message,
)

if TYPE_CHECKING:
    from evorobotics.evolution import EvolutionResult, GenerationSummary
    from evorobotics.strategies import Archive
    from schemas.run import RunConfig

LOG_LINES = 20
"""Roughly how many progress lines a non-terminal run prints (plus the last generation)."""
COMPILING = "compiling the simulator, once per machine: about 15 s"
"""Said before a run whose kernels are not compiled yet (`evorobotics.sim.kernel_cached`):
else the first generation would keep the progress bar at 0 that long without a word."""


def resolve_config(config_file: Path | None, overrides: dict[str, Any]) -> RunConfig:
    """Defaults < config file < flags (None = not given); ConfigError with a one-line reason."""
    from pydantic import ValidationError

    from evorobotics.errors import EvoError
    from evorobotics.evaluate import check_config
    from schemas.run import RunConfig

    data: dict[str, Any] = {}
    if config_file is not None:
        try:
            loaded = json.loads(config_file.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ConfigError(f"config file {config_file}: {err}") from None
        if not isinstance(loaded, dict):
            raise ConfigError(f"config file {config_file}: expected a JSON object")
        data.update(loaded)
    given = {k: v for k, v in overrides.items() if v is not None}
    maze = given.get("maze")
    if "maze" in given:
        given["maze"] = maze_value(given["maze"])
    if "network" in given:
        given["network"] = network_value(given["network"])
    data.update(given)
    try:
        config = RunConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(validation_message(err)) from None
    try:
        check_config(config)
    except (EvoError, ValueError) as err:
        raise ConfigError(name_maze_file(f"maze: {err}", maze)) from None
    return config


def write_generations_csv(path: Path, history: tuple[GenerationSummary, ...]) -> None:
    """`generation,best,mean,worst`; floats as repr so they parse back to the same bits."""
    with path.open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(["generation", "best", "mean", "worst"])
        for h in history:
            writer.writerow([h.generation, repr(h.best), repr(h.mean), repr(h.worst)])


def write_archive_csv(path: Path, config: RunConfig, archive: Archive) -> None:
    """One row per archive entry: its two descriptors (named by the axes), its fitness and the
    sha256 of its controller document; floats as repr so they parse back to the same bits."""
    from evorobotics.document import controller_sha256

    spec = config.network_spec
    with path.open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow([*config.strategy_settings.axes, "fitness", "sha256"])
        for d, fit, genome in zip(
            archive.descriptors, archive.fitness, archive.genomes, strict=True
        ):
            writer.writerow(
                [
                    repr(float(d[0])),
                    repr(float(d[1])),
                    repr(float(fit)),
                    controller_sha256(spec, genome),
                ]
            )


@contextmanager
def _importing() -> Iterator[None]:
    """Import the simulator or matplotlib with the cyclic garbage collector off, then freeze
    what is there (`gc.freeze`): collections would only walk module objects, which live on
    (about 0.1 s while importing, 0.15 s more at exit)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


def _plot_loop(connection: Connection) -> None:
    """The plotter process: import matplotlib, then draw each (plot function name, args)
    received, answering None or the error's line, until None."""
    with _importing():
        from evorobotics import plots

    figures: dict[str, Callable[..., None]] = {
        f.__name__: f
        for f in (plots.fitness_plot, plots.paths_plot, plots.network_plot, plots.archive_plot)
    }
    while (request := connection.recv()) is not None:
        name, args = request
        try:
            figures[name](*args)
        except Exception as exc:  # the command reports it and fails
            connection.send(f"{name}: {type(exc).__name__}: {exc}")
        else:
            connection.send(None)


class PlotError(Exception):
    """A plot could not be drawn (its function's error, or the plotter process is gone)."""


class Plotter:
    """The run's plots drawn by a process started with the command: its matplotlib import
    (about 0.3 s) overlaps this process's imports of the simulator, and it draws while this
    one goes on (fitness.png during the champion's validation). Spawned, not forked: the
    caller may hold threads (a test runner)."""

    def __init__(self) -> None:
        context = multiprocessing.get_context("spawn")
        self._connection, theirs = context.Pipe()
        self._process = context.Process(target=_plot_loop, args=(theirs,), daemon=True)
        self._process.start()
        theirs.close()
        self._pending = 0

    def draw(self, name: str, *args: Any) -> None:
        """Send `evorobotics.plots.<name>(*args)` to be drawn."""
        self._connection.send((name, args))
        self._pending += 1

    def wait(self) -> None:
        """Return once every figure sent is written; PlotError naming one that failed."""
        try:
            answers = [self._connection.recv() for _ in range(self._pending)]
        except EOFError:
            raise PlotError("the plotter process exited") from None
        self._pending = 0
        failed = [a for a in answers if a is not None]
        if failed:
            raise PlotError(f"plot failed: {failed[0]}")

    def close(self) -> None:
        """Stop the process (its figures are written or no longer wanted)."""
        self._process.kill()
        self._process.join()
        self._connection.close()


def write_outputs(
    out: Path, config: RunConfig, result: EvolutionResult, plotter: Plotter
) -> list[Path]:
    """best.json, generations.csv, config.json and the three plots, and archive.csv and
    archive.png for a strategy with an archive; returns the paths once all are written. The
    plots are drawn by `plotter` (the champion's paths simulated here; fitness.png may have
    been sent already)."""
    from evorobotics.evaluate import unseen_paths

    out.mkdir(parents=True, exist_ok=True)
    files = {
        name: out / name
        for name in (
            "best.json",
            "generations.csv",
            "config.json",
            "fitness.png",
            "paths.png",
            "network.png",
        )
    }
    best = result.best
    plotter.draw("paths_plot", config, best, files["paths.png"], unseen_paths(config, best.weights))
    plotter.draw("network_plot", best.spec, best.weights, files["network.png"])
    if result.archive is not None:
        files["archive.csv"] = out / "archive.csv"
        files["archive.png"] = out / "archive.png"
        plotter.draw("archive_plot", config, result.archive, files["archive.png"])
        write_archive_csv(files["archive.csv"], config, result.archive)
    files["best.json"].write_text(best.to_json())
    write_generations_csv(files["generations.csv"], result.history)
    files["config.json"].write_text(config.model_dump_json(indent=2) + "\n")
    plotter.wait()
    return list(files.values())


def _line(s: GenerationSummary, total: int, best_so_far: float) -> str:
    return (
        f"generation {s.generation + 1}/{total} training fitness: best {s.best:.4f} "
        f"mean {s.mean:.4f} worst {s.worst:.4f}"
        + (f" nan {s.nan_count}" if s.nan_count else "")
        + f"; best so far {best_so_far:.4f}"
    )


@contextmanager
def _progress(total: int) -> Iterator[Callable[[GenerationSummary], None]]:
    """A rich bar on a terminal; otherwise a plain line every ~total/LOG_LINES generations.
    Both give the best training fitness so far beside the generation's best, which falls
    as well as rises (every generation trains on new start poses)."""
    top = -math.inf

    def best_so_far(s: GenerationSummary) -> float:
        nonlocal top
        top = max(top, s.best)
        return top

    if sys.stdout.isatty():
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

        with Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
        ) as bar:
            task = bar.add_task("evolving", total=total)

            def tick(s: GenerationSummary) -> None:
                label = training_progress(best_so_far(s), s.best)
                bar.update(task, advance=1, description=label)

            yield tick
        return
    every = max(1, total // LOG_LINES)

    def log(s: GenerationSummary) -> None:
        so_far = best_so_far(s)
        if (s.generation + 1) % every == 0 or s.generation + 1 == total:
            print(_line(s, total, so_far), flush=True)

    yield log


def evolve_command(
    population: Annotated[int | None, typer.Option(help="individuals per generation [100]")] = None,
    generations: Annotated[int | None, typer.Option(help="generations [350]")] = None,
    trials: Annotated[int | None, typer.Option(help="trials per individual [3]")] = None,
    steps: Annotated[int | None, typer.Option(help="time steps per trial [40]")] = None,
    seed: Annotated[int | None, typer.Option(help="run seed [0]")] = None,
    maze: Annotated[
        str | None, typer.Option(metavar="NAME_OR_FILE", help="shipped maze name or maze file")
    ] = None,
    network: Annotated[
        str | None,
        typer.Option(metavar="PRESET_OR_FILE", help="network preset or NetworkSpec JSON file"),
    ] = None,
    nominal: NominalOpt = False,
    strategy: Annotated[
        str | None,
        typer.Option(
            metavar="NAME",
            help="paper-ga, cma-es, sep-cma-es, map-elites, cma-me or novelty [paper-ga]",
        ),
    ] = None,
    config: Annotated[
        Path | None, typer.Option("--config", metavar="FILE", help="a RunConfig JSON")
    ] = None,
    out: Annotated[Path, typer.Option(help="output directory")] = Path("out"),
    tensorboard: Annotated[
        Path | None,
        typer.Option(metavar="DIR", help="also write TensorBoard event files into DIR"),
    ] = None,
    threads: Annotated[
        int | None,
        typer.Option(help="simulation threads; the result is the same [cores available]"),
    ] = None,
) -> None:
    """Evolve a controller in one process (defaults: the paper's experiment) and plot it."""
    overrides: dict[str, Any] = {
        "population": population,
        "generations": generations,
        "trials": trials,
        "steps": steps,
        "seed": seed,
        "maze": maze,
        "network": network,
        "reality_gap": "off" if nominal else None,
        "strategy": strategy,
    }
    if threads is not None and threads < 1:
        typer.echo(f"colony evolve: invalid threads: must be >= 1, got {threads}", err=True)
        raise typer.Exit(code=2)
    # numpy's and scipy's OpenBLAS would start a thread per core, each spinning about 0.1 s of
    # CPU as it loads: the run uses no BLAS worth a thread (the plotter inherits this)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    plotter = Plotter()  # first: it imports matplotlib while this process imports numba
    try:
        _evolve(config, overrides, out, tensorboard, threads, plotter)
    except PlotError as err:
        typer.echo(f"colony evolve: {err}", err=True)
        raise typer.Exit(code=1) from None
    finally:
        plotter.close()


def _evolve(
    config: Path | None,
    overrides: dict[str, Any],
    out: Path,
    tensorboard: Path | None,
    threads: int | None,
    plotter: Plotter,
) -> None:
    """`evolve_command` once its plotter is started."""
    # numba and the simulator: only when evolving, so `colony --help` stays fast
    with _importing():
        from evorobotics.evaluate import available_cores, trial_steps
        from evorobotics.evolution import evolve
        from evorobotics.sim import kernel_cached

        try:
            cfg = resolve_config(config, overrides)  # loads the compiled kernels
        except ConfigError as err:
            typer.echo(f"colony evolve: invalid {err}", err=True)
            raise typer.Exit(code=2) from None
    spec = cfg.network_spec
    workers = available_cores() if threads is None else threads
    typer.echo(
        f"evolving: population {cfg.population}, {cfg.generations} generations, "
        f"{cfg.trials} x {trial_steps(cfg)} steps, {spec.weight_count} weights, seed {cfg.seed}, "
        f"strategy {cfg.strategy}, {workers} threads"
    )
    if not kernel_cached(spec):
        typer.echo(COMPILING)
    started = time.perf_counter()
    events = None
    if tensorboard is not None:
        from server.runs.tracking import RunEvents  # tensorboardX only when asked for

        events = RunEvents(tensorboard)
    told_last = started  # after the last generation, `evolve` picks the champion: validation
    history: list[GenerationSummary] = []
    with _progress(cfg.generations) as report:

        def on_generation(s: GenerationSummary) -> None:
            nonlocal told_last
            report(s)
            if events is not None:
                events.generation(s.generation, best=s.best, mean=s.mean)
            history.append(s)
            if len(history) == cfg.generations:  # drawn while the champion is validated
                out.mkdir(parents=True, exist_ok=True)
                plotter.draw("fitness_plot", history, out / "fitness.png")
            told_last = time.perf_counter()

        result = evolve(cfg, on_generation=on_generation, threads=workers)
    validated = time.perf_counter() - told_last
    if events is not None:
        if result.best.validation is not None:
            events.validation(result.history[-1].generation, result.best.validation)
        events.close()
    evolved = time.perf_counter() - started
    files = write_outputs(out, cfg, result, plotter)
    total = time.perf_counter() - started
    best = result.best
    for line in champion_lines(best.sha256, best.fitness, best.validation, best.test):
        typer.echo(line)
    typer.echo(f"wrote {', '.join(str(p) for p in files)}")
    typer.echo(
        f"wall time {total:.2f} s (evolution {evolved:.2f} s, of which validation "
        f"{validated:.2f} s; files {total - evolved:.2f} s)"
    )
