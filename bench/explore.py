"""Do validated champions explore? Seeds x networks: evolve, then explore the champion.

For each seed s (`--seeds N`: 0..N-1, default 10) and network n (`--networks`, default
paper-best and reactive), evolves RunConfig(seed=s, network=n) with every other setting
default (`evorobotics.evolution.evolve`, validated champion included), then measures its
champion with `evorobotics.explore.explore` over `--poses` (1,000) unseen start poses x
`--steps` (1,000) steps: the exploration stream of seed 12345, which no run trains or validates
on, in the run's world, twice: in the nominal world and with every trial's robot drawn from
the paper's whole reality gap (`--reality-gap` of `colony evaluate`). Then under the gap in
mazes no run trains on (`--mazes`: two generated ones and the dead-end maze `deadends`).
Prints per seed: training fitness, the champion's validation score, stuck and roaming, then
roaming, stuck by 40/200/H steps, confined; per network and world: median, range and mean with
a 95 % t confidence interval; the wall time of validation against the whole run (issue 23
wants at most 20 %); and the random Eq 7 population (generation 0) as a reference.

Run: .venv/bin/python bench/explore.py [--seeds N] [--networks A B] [--generations G]
[--config JSON] [--poses P] [--steps H] [--mazes M ...] [--quick]   (--quick: 2 seeds, 30 generations, for a smoke run)

`--speed` measures instead how fast a champion's report runs (`--poses` 4,000 x `--steps`
1,000, one thread; the champion of the nominal paper experiment, or `--controller FILE`):
in this process, interleaved, the kernel's watched trials against today's definition (every
pose recorded, then `explore.trials`) and the independent numpy simulator on the same work
(`sim.simulate_reference`, recorded, plus `explore.trials`), each report's rows checked equal;
then, with `--against DIR` (a checkout of another commit), `colony evaluate` as a process from
this tree and from DIR in turn, net of its start-up (the same command with one pose of one
step), the reports checked equal to the digit. Robot-steps per second per core; medians of
`--rounds` rounds and the load average.
    .venv/bin/python bench/explore.py --speed --against /tmp/before
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evorobotics.document import ControllerDocument
from evorobotics.evaluate import start_poses
from evorobotics.evolution import GenerationSummary, RunLoop, evolve
from evorobotics.explore import (
    Exploration,
    exploration,
    explore,
    trials,
    watch,
    watched_trials,
)
from evorobotics.maze import load_maze
from evorobotics.seeds import Purpose
from evorobotics.sim import simulate, simulate_reference
from schemas.run import RunConfig

ROOT = Path(__file__).resolve().parents[1]

TEST_SEED = 12345
"""Seed of the exploration start poses every controller is measured on."""
RANDOM_CONTROLLERS = 20
"""Controllers of generation 0 (Eq 7) in the random reference row."""
UNSEEN_MAZES = ("gen:5:1", "gen:5:2", "deadends")
"""Mazes no default run trains on, where champions are measured under the gap."""
WORLDS = ("nominal", "gap")
"""The paper maze's two measures of every controller."""


@dataclass(frozen=True)
class Row:
    label: str
    seed: int | None
    trained: float | None
    """Training fitness of the champion (None for a random controller)."""
    validation: tuple[float, float, float] | None
    """The champion's validation score, stuck and roaming fractions."""
    by: dict[str, Exploration]
    """"nominal" and "gap" in the paper maze, then each unseen maze under the gap."""


def t_quantile_975(df: int) -> float:
    """The 0.975 quantile of Student's t with `df` degrees of freedom (numpy only).

    The density integrated from 0 by the trapezoid rule on a fine grid, then inverted; exact
    to about 1e-6, plenty for a confidence interval of a handful of seeds.
    """
    x = np.linspace(0.0, 60.0, 600_001)
    log_c = math.lgamma((df + 1) / 2) - math.lgamma(df / 2) - 0.5 * math.log(df * math.pi)
    pdf = np.exp(log_c - (df + 1) / 2 * np.log1p(x * x / df))
    cdf = 0.5 + np.concatenate([[0.0], np.cumsum((pdf[1:] + pdf[:-1]) / 2 * np.diff(x))])
    return float(np.interp(0.975, cdf, x))


def summary(values: list[float]) -> str:
    """Median [min, max], mean +- the 95 % t interval's half-width (n/a for one value)."""
    v = np.asarray(values, dtype=np.float64)
    middle = f"{np.median(v):7.3f} [{v.min():.3f}, {v.max():.3f}]"
    if len(v) < 2:
        return f"{middle}  mean {v.mean():.3f} (CI n/a)"
    half = t_quantile_975(len(v) - 1) * float(v.std(ddof=1)) / math.sqrt(len(v))
    return f"{middle}  mean {v.mean():.3f} +- {half:.3f}"


def measure(
    config: RunConfig,
    weights: np.ndarray,
    poses: int,
    steps: int,
    mazes: tuple[str, ...] = (),
    worlds: tuple[str, ...] = WORLDS,
) -> dict[str, Exploration]:
    """The run's maze in `worlds` (nominal, under the gap), then each of `mazes` under the gap."""

    def one(maze: str, gap: bool) -> Exploration:
        return explore(
            config.network_spec,
            weights,
            poses=poses,
            steps=steps,
            maze=maze,
            seed=TEST_SEED,
            reality_gap=gap,
            world=config.world,
            fitness_weights=config.fitness,
        )

    found = {world: one(config.maze, world == "gap") for world in worlds}
    return found | {maze: one(maze, True) for maze in mazes}


def evolved(
    config: RunConfig, poses: int, steps: int, mazes: tuple[str, ...]
) -> tuple[Row, Row, float, float]:
    """The champion's row, training rank 0's row (what a run exported without validation), and
    the run's wall time in training and in validation (s).

    Validation is what `evolve` does after the last generation's summary (`champion`).
    """
    told_at: list[float] = []

    def on_generation(_: GenerationSummary) -> None:
        told_at.append(time.perf_counter())

    t0 = time.perf_counter()
    result = evolve(config, on_generation=on_generation)
    t1 = time.perf_counter()
    best = result.best
    v = best.validation
    row = Row(
        str(config.network),
        config.seed,
        best.fitness,
        None if v is None else (v.score, v.stuck, v.roaming),
        measure(config, np.asarray(best.weights), poses, steps, mazes),
    )
    fitness = np.where(np.isfinite(result.fitness), result.fitness, -np.inf)
    top = int(np.argmax(fitness))  # training rank 0: the fittest, ties to the lower index
    rank0 = Row(
        f"{config.network} rank 0",
        config.seed,
        float(result.fitness[top]),
        None,
        measure(config, np.asarray(result.genomes[top]), poses, steps),
    )
    return row, rank0, told_at[-1] - t0, t1 - told_at[-1]


def effect(label: str, a: list[float], b: list[float], *, paired: bool) -> None:
    """Mean difference a - b with its 95 % t interval, and Cohen's d (paired: mean / sd of the
    differences; unpaired: over the pooled sd)."""
    x, y = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if paired:
        d = x - y
        diff, sd, df = float(d.mean()), float(d.std(ddof=1)), len(d) - 1
        half = t_quantile_975(df) * sd / math.sqrt(len(d))
    else:
        diff = float(x.mean() - y.mean())
        vx, vy = float(x.var(ddof=1)), float(y.var(ddof=1))
        sd = math.sqrt(((len(x) - 1) * vx + (len(y) - 1) * vy) / (len(x) + len(y) - 2))
        half = t_quantile_975(len(x) + len(y) - 2) * sd * math.sqrt(1 / len(x) + 1 / len(y))
    cohen = f"{diff / sd:+.2f}" if sd > 0 else "n/a (no spread)"
    print(f"  {label:46s} {diff:+.3f} +- {half:.3f} (95 % CI), Cohen's d {cohen}")


def print_rows(rows: list[Row], steps: int, world: str) -> None:
    print(
        f"{'network':12s} {'seed':>4s} {'train F':>8s} {'val F':>7s} {'val stuck':>9s} "
        f"{'val roam':>8s} {'roaming':>7s} {'stuck40':>7s} {'stuck200':>8s} "
        f"{f'stuck{steps}':>9s} {'confined':>8s} {f'offset{steps} m':>12s}"
    )
    for r in rows:
        trained = "-" if r.trained is None else f"{r.trained:.2f}"
        val = ("-", "-", "-") if r.validation is None else tuple(f"{x:.2f}" for x in r.validation)
        seed = "-" if r.seed is None else str(r.seed)
        e = r.by[world]
        print(
            f"{r.label:12s} {seed:>4s} {trained:>8s} {val[0]:>7s} {val[1]:>9s} {val[2]:>8s} "
            f"{e.roaming:7.3f} {e.stuck[40]:7.3f} {e.stuck[200]:8.3f} {e.stuck[steps]:9.3f} "
            f"{e.confined:8.3f} {e.max_offset[steps]:12.3f}"
        )


def print_summary(label: str, rows: list[Row], steps: int, world: str) -> None:
    print(f"{label} ({len(rows)} controllers, {world}): median [range]  mean +- 95 % CI")
    measures = {
        "roaming": [r.by[world].roaming for r in rows],
        "stuck by 40": [r.by[world].stuck[40] for r in rows],
        "stuck by 200": [r.by[world].stuck[200] for r in rows],
        f"stuck by {steps}": [r.by[world].stuck[steps] for r in rows],
        f"max offset by {steps}, m": [r.by[world].max_offset[steps] for r in rows],
    }
    for name, values in measures.items():
        print(f"  {name:22s} {summary(values)}")


def champion(controller: Path | None, generations: int | None) -> ControllerDocument:
    """The controller of `--controller`, or the champion of the nominal paper experiment (of
    `generations`, by default the paper's)."""
    if controller is not None:
        return ControllerDocument.from_json(controller.read_text())
    config = RunConfig(reality_gap="off")
    return evolve(config.model_copy(update={"generations": generations or config.generations})).best


def load() -> str:
    """The machine's load averages (1, 5, 15 minutes)."""
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def in_process(doc: ControllerDocument, poses: int, steps: int, rounds: int) -> tuple[float, float]:
    """Rows of the report's trials (seed 0, the document's world) three ways, the kernel's
    interleaved: print each one's robot-steps/s (median of rounds) and return the watched
    kernel's and the numpy reference's."""
    world = doc.world or RunConfig().world
    maze = load_maze("paper")
    starts = start_poses(maze, 0, 0, poses, world, Purpose.EXPLORATION)
    weights = np.repeat(doc.weights[None], poses, axis=0)

    def watched() -> np.ndarray:
        return watched_trials(watch(doc.spec, weights, maze, starts, steps, world))

    def recorded() -> np.ndarray:
        run = simulate(doc.spec, weights, maze, starts, steps, world, record=True)
        return trials(run, steps)

    def reference() -> np.ndarray:
        run = simulate_reference(doc.spec, weights, maze, starts, steps, world, record=True)
        return trials(run, steps)

    ways: dict[str, Callable[[], np.ndarray]] = {
        "kernel, watched (this tree)": watched,
        "kernel, every pose recorded, then explore.trials (today's definition)": recorded,
    }
    rows = {name: way() for name, way in ways.items()}  # warm-up (compilation) and the rows
    times: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(rounds):
        for name, way in ways.items():
            t0 = time.perf_counter()
            way()
            times[name].append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    numpy_rows = reference()
    numpy_s = time.perf_counter() - t0
    work = poses * steps
    print(f"{poses} poses x {steps} steps of one champion in this process, one thread:")
    for name, seconds in times.items():
        print(f"  {name:72s} {work / statistics.median(seconds) / 1e6:7.2f} M robot-steps/s")
    print(f"  {'numpy reference simulator, recorded, then explore.trials (once)':72s} "
          f"{work / numpy_s / 1e6:7.2f} M robot-steps/s")  # fmt: skip
    watched_rows, recorded_rows = rows.values()
    same = watched_rows.tobytes() == recorded_rows.tobytes()
    print(
        f"  the kernel's rows, watched and recorded, bit for bit equal: {'yes' if same else 'NO'}"
    )
    # numpy's libm sin and cos round unlike the kernel's polynomials: trials drift apart
    kernel_e = exploration(watched_rows, steps, "paper", 0, False)
    numpy_e = exploration(numpy_rows, steps, "paper", 0, False)
    print(
        f"  roaming {kernel_e.roaming:.3f} (numpy reference {numpy_e.roaming:.3f}), coverage "
        f"{kernel_e.coverage:.1f} ({numpy_e.coverage:.1f}) cells"
    )
    return work / statistics.median(times["kernel, watched (this tree)"]), work / numpy_s


def colony(tree: Path, cwd: Path, *args: str) -> tuple[float, str]:
    """Wall time and output of one `colony ARGS` process run from `tree`'s code."""
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", "from colony.cli import main; main()", *args],
        env={**os.environ, "PYTHONPATH": str(tree)}, cwd=cwd, capture_output=True, text=True,
    )  # fmt: skip
    wall = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"colony {' '.join(args)} from {tree} failed:\n{done.stderr[-2000:]}")
    return wall, done.stdout


def against(tree: Path, doc: ControllerDocument, poses: int, steps: int, rounds: int) -> None:
    """`colony evaluate` from this tree and from `tree`, interleaved: net robot-steps/s."""
    trees = {"this tree": ROOT, str(tree): tree}
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)  # off any checkout, as `python -c` puts cwd first on the path
        (cwd / "champion.json").write_text(doc.to_json())
        # one thread (a tree without --threads evaluates on one)
        flags = {
            name: ["--threads", "1"]
            if "--threads" in colony(t, cwd, "evaluate", "--help")[1]
            else []
            for name, t in trees.items()
        }

        def run(name: str, n: int, h: int) -> tuple[float, str]:
            size = ["--poses", str(n), "--steps", str(h), "--json", *flags[name]]
            return colony(trees[name], cwd, "evaluate", "champion.json", *size)

        reports = {name: run(name, poses, steps)[1] for name in trees}  # and warm caches
        runs: dict[str, dict[str, list[float]]] = {n: {"big": [], "start": []} for n in trees}
        for _ in range(rounds):
            for name in trees:
                runs[name]["big"].append(run(name, poses, steps)[0])
                runs[name]["start"].append(run(name, 1, 1)[0])
    print(f"colony evaluate, one thread, {poses} x {steps}, interleaved (median of {rounds}):")
    rates = {}
    for name, r in runs.items():
        big, start = statistics.median(r["big"]), statistics.median(r["start"])
        rates[name] = poses * steps / (big - start)
        print(
            f"  {name}: {big:.2f} s, start-up (1 pose x 1 step) {start:.2f} s: "
            f"{rates[name] / 1e6:.2f} M robot-steps/s net of start-up"
        )
    mine, other = rates.values()
    print(f"  ratio, this tree / {tree}: {mine / other:.1f}x")
    print(f"  reports equal to the digit: {'yes' if len(set(reports.values())) == 1 else 'NO'}")


def speed(args: argparse.Namespace) -> None:
    print(f"load average before: {load()}")
    doc = champion(args.controller, args.generations)
    kernel, numpy_rate = in_process(doc, args.poses, args.steps, args.rounds)
    print(f"  watched kernel / numpy reference: {kernel / numpy_rate:.0f}x (target >= 40x)")
    if args.against is not None:
        against(args.against, doc, args.poses, args.steps, args.rounds)
    print(f"load average after: {load()}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=None, help="run seeds 0..N-1 (10)")
    parser.add_argument("--networks", nargs="+", default=["paper-best", "reactive"])
    parser.add_argument("--generations", type=int, default=None, help="(the default run's)")
    parser.add_argument("--poses", type=int, help="(1000; 4000 with --speed)")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument(
        "--config",
        default="{}",
        help="RunConfig fields every run sets, as JSON, e.g. '{\"steps\": 240}' (default: none)",
    )
    parser.add_argument("--mazes", nargs="*", default=list(UNSEEN_MAZES), help="unseen mazes")
    parser.add_argument("--quick", action="store_true", help="2 seeds, 30 generations")
    parser.add_argument("--speed", action="store_true", help="how fast a report runs, instead")
    parser.add_argument("--controller", type=Path, help="--speed: this controller document")
    parser.add_argument("--against", type=Path, help="--speed: a checkout of another commit")
    parser.add_argument("--rounds", type=int, default=3, help="--speed: interleaved rounds")
    args = parser.parse_args()
    if args.speed:
        args.poses = args.poses or 4000
        speed(args)
        return
    args.poses = args.poses or 1000
    if args.steps < 200:
        parser.error("--steps must be >= 200 (stuck is reported at 40 and 200 steps too)")
    try:
        overrides = json.loads(args.config)
        RunConfig.model_validate(overrides)
    except ValueError as exc:
        parser.error(f"--config: {' '.join(str(exc).split()[:20])}")
    seeds = args.seeds if args.seeds is not None else 2 if args.quick else 10
    generations = args.generations or (30 if args.quick else RunConfig().generations)

    rows: dict[str, list[Row]] = {}
    unvalidated: dict[str, list[Row]] = {}
    training = validation = 0.0
    for network in args.networks:
        rows[network], unvalidated[network] = [], []
        for seed in range(seeds):
            config = RunConfig.model_validate(
                {**overrides, "seed": seed, "network": network, "generations": generations}
            )
            row, rank0, trained_s, validated_s = evolved(
                config, args.poses, args.steps, tuple(args.mazes)
            )
            rows[network].append(row)
            unvalidated[network].append(rank0)
            training += trained_s
            validation += validated_s
            print(
                f"{network} seed {seed}: {generations} generation(s) in {trained_s:.1f} s, "
                f"validation {validated_s:.2f} s, roaming {row.by['nominal'].roaming:.3f} "
                f"nominal, {row.by['gap'].roaming:.3f} under the gap",
                flush=True,
            )

    base = RunConfig(network=args.networks[0], generations=generations)
    random_genomes = RunLoop(base).ask()[:RANDOM_CONTROLLERS]  # generation 0: Eq 7
    randoms = [
        Row(
            f"random {args.networks[0]}", None, None, None, measure(base, g, args.poses, args.steps)
        )
        for g in random_genomes
    ]

    champions = [r for network in args.networks for r in rows[network]]
    ranks0 = [r for network in args.networks for r in unvalidated[network]]
    for world in WORLDS:
        print()
        print(
            f"champions over {args.poses} unseen start poses x {args.steps} steps (exploration "
            f"stream, seed {TEST_SEED}, maze {base.maze!r}, each run's world, {world})"
        )
        print_rows(champions, args.steps, world)
        print_rows(ranks0, args.steps, world)
        print()
        for network in args.networks:
            print_summary(
                f"evolved {network}, validated champion", rows[network], args.steps, world
            )
            print_summary(
                f"evolved {network}, training rank 0 (no validation)",
                unvalidated[network],
                args.steps,
                world,
            )
        print_summary(
            f"random {args.networks[0]} (generation 0 of seed 0, Eq 7)", randoms, args.steps, world
        )
        if seeds >= 2:
            print()
            print(f"effects on roaming (fraction of unseen trials, {world}):")
            for network in args.networks:
                effect(
                    f"{network}: champion - training rank 0 (paired)",
                    [r.by[world].roaming for r in rows[network]],
                    [r.by[world].roaming for r in unvalidated[network]],
                    paired=True,
                )
            for other in args.networks[1:]:
                effect(
                    f"{args.networks[0]} - {other} (champions)",
                    [r.by[world].roaming for r in rows[args.networks[0]]],
                    [r.by[world].roaming for r in rows[other]],
                    paired=False,
                )
    if args.mazes:
        print()
        print(f"champions in unseen mazes under the gap, {args.poses} poses x {args.steps} steps")
        for maze in args.mazes:
            for network in args.networks:
                print_summary(f"{network} champions in {maze!r}", rows[network], args.steps, maze)
    total = training + validation
    print()
    print(
        f"wall time over all runs: training {training:.1f} s, validation {validation:.1f} s: "
        f"validation share {100 * validation / total:.1f} % of a run (target <= 20 %)"
    )


if __name__ == "__main__":
    main()
