"""Which strategy evolves the best explorer? Strategies x seeds, each champion explored in the
paper maze and in generated mazes never used in training (issue 26, "The comparison").

For each strategy (`--strategies`) and seed 0..N-1 (`--seeds`, default 10), evolves the paper's
experiment in the nominal world (RunConfig's defaults but `strategy`, `seed` and `reality_gap:
"off"`: population 100 x 350 generations, the same evaluation budget for every strategy) with `evorobotics.evolution.evolve`, which ends
with the validated champion, in `--jobs` worker processes. Each champion is written to `--out`
as a controller document (`STRATEGY-pPOP-gGEN-seedS.json`); `--reuse` explores the ones found
there instead of evolving them again. Every champion is then explored (bench/explore.py's
`measure`: `--poses` unseen start poses x `--steps` steps, the exploration stream of seed
12345, nominal) in the paper maze and in each of `--mazes` (generated, checked connected and roomy
first). Prints per strategy x maze the median [bootstrap 95 % CI] of roaming, stuck by the
horizon and coverage; per maze, Mann-Whitney U between every pair of strategies on roaming and
stuck (Holm-corrected over that maze's comparisons, Vargha-Delaney A12) and the verdicts
(`evorobotics.stats`); whether the issue's targets hold; and writes box plots of roaming per
strategy x maze (`--png`).

    .venv/bin/python bench/strategies_study.py [--strategies S ...] [--seeds 10] [--jobs 2]
        [--out DIR] [--reuse] [--generations G] [--poses 1000] [--steps 1000]
        [--mazes gen:5:1 gen:5:2] [--png PATH] [--quick]
    (--quick: 2 seeds, 20 generations, 100 poses x 200 steps, the png in --out)
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import get_args

import numpy as np
from explore import TEST_SEED, measure

from evorobotics.document import ControllerDocument
from evorobotics.evolution import evolve
from evorobotics.explore import Exploration
from evorobotics.maze import CORRIDOR_CELLS, load_maze
from evorobotics.stats import Summary, compare, summarize, verdicts
from schemas.run import RunConfig, StrategyName
from schemas.world import World

STRATEGIES: tuple[StrategyName, ...] = get_args(StrategyName)
TRAINING_MAZE = "paper"
GENERATED_MAZES = ("gen:5:1", "gen:5:2")
"""26 x 26 cells of 0.1 m (2.6 m across; the paper maze is 2.4 m), 0.4 m corridors."""
DEFAULT_PNG = Path(__file__).resolve().parents[1] / "docs" / "img" / "strategies-roaming.png"
COMPARED = ("roaming", "stuck")
"""Metrics tested between strategies (coverage is summarised only)."""
TARGET_ROAMING, TARGET_STUCK, TARGET_GENERATED = 0.90, 0.05, 0.70
"""Issue 26: the best strategy's median roaming and stuck in the paper maze, roaming elsewhere."""


@dataclass(frozen=True)
class Task:
    """One run of the study: evolve (or reuse) a champion, explore it in every maze."""

    strategy: StrategyName
    seed: int
    generations: int
    out: Path
    reuse: bool
    mazes: tuple[str, ...]
    poses: int
    steps: int

    @property
    def config(self) -> RunConfig:
        return RunConfig(
            strategy=self.strategy,
            seed=self.seed,
            generations=self.generations,
            reality_gap="off",
        )

    @property
    def path(self) -> Path:
        c = self.config
        return self.out / f"{self.strategy}-p{c.population}-g{c.generations}-seed{self.seed}.json"


@dataclass(frozen=True)
class Outcome:
    strategy: StrategyName
    seed: int
    evolved_s: float | None
    """Wall time of evolve (validation included); None when the champion was reused."""
    explored: dict[str, Exploration]
    """maze -> the champion's exploration report there."""


def run(task: Task) -> Outcome:
    """Evolve (or load) the champion of `task`, write it, explore it in every maze."""
    config = task.config
    evolved_s: float | None = None
    if task.reuse and task.path.exists():
        champion = ControllerDocument.from_json(task.path.read_text())
        if champion.spec != config.network_spec:
            raise ValueError(f"{task.path}: not a champion of this study's network")
    else:
        began = time.perf_counter()
        champion = evolve(config).best
        evolved_s = time.perf_counter() - began
        partial = task.path.with_suffix(".part")
        partial.write_text(champion.to_json())
        partial.replace(task.path)
    weights = np.asarray(champion.weights)
    explored = {
        maze: measure(
            config.model_copy(update={"maze": maze}),
            weights,
            task.poses,
            task.steps,
            worlds=("nominal",),
        )["nominal"]
        for maze in task.mazes
    }
    return Outcome(task.strategy, task.seed, evolved_s, explored)


def describe_maze(spec: str) -> str:
    """One line on a generated maze; SystemExit unless its free cells are all connected and its
    corridors wider than the robot's body diagonal (room to turn)."""
    maze = load_maze(spec)
    free = ~maze.grid
    reached = np.zeros_like(free)
    reached[np.unravel_index(int(np.argmax(free)), free.shape)] = True
    while True:  # flood fill by 4-neighbour dilation inside the free cells
        grown = reached.copy()
        grown[1:] |= reached[:-1]
        grown[:-1] |= reached[1:]
        grown[:, 1:] |= reached[:, :-1]
        grown[:, :-1] |= reached[:, 1:]
        grown &= free
        if (grown == reached).all():
            break
        reached = grown
    world = World()
    corridor = CORRIDOR_CELLS * maze.cell_size
    diagonal = float(np.hypot(world.body_length, world.body_width))
    if not (reached == free).all() or corridor <= diagonal:
        raise SystemExit(f"maze {spec}: free cells not all connected or corridors too narrow")
    return (
        f"{spec}: {maze.grid.shape[0]} x {maze.grid.shape[1]} cells ({maze.width:.1f} m across), "
        f"{int(free.sum())} free cells all connected, corridors {corridor:.1f} m (body "
        f"diagonal {diagonal:.2f} m)"
    )


def cell(s: Summary) -> str:
    return f"{s.median:.3f} [{s.ci_low:.3f}, {s.ci_high:.3f}]"


def best_strategy(medians: dict[str, dict[str, float]]) -> str:
    """Highest median roaming in the training maze; ties to the lower median stuck."""
    return max(medians, key=lambda s: (medians[s]["roaming"], -medians[s]["stuck"]))


def target(label: str, value: float, bound: float, at_least: bool) -> bool:
    """Print one target's line; whether the median meets it."""
    held = value >= bound if at_least else value <= bound
    print(
        f"  {label} {'>=' if at_least else '<='} {bound:.2f}: median {value:.3f} {'yes' if held else 'NO'}"
    )
    return held


def plot(samples: dict[str, dict[str, list[float]]], mazes: tuple[str, ...], path: Path) -> None:
    """Box plots of roaming per strategy, one panel per maze, each seed's champion a dot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    strategies = list(samples)
    fig, axes = plt.subplots(
        1, len(mazes), figsize=(4.2 * len(mazes), 4.2), sharey=True, squeeze=False
    )
    jitter = np.random.default_rng(0)
    for ax, maze in zip(axes[0], mazes, strict=True):
        data = [samples[s][maze] for s in strategies]
        ax.boxplot(data, showfliers=False)
        for i, values in enumerate(data, start=1):
            ax.plot(i + jitter.uniform(-0.12, 0.12, len(values)), values, ".", alpha=0.6)
        ax.set_xticks(range(1, len(strategies) + 1), strategies, rotation=30)
        ax.set_title(f"{maze}{' (training maze)' if maze == TRAINING_MAZE else ''}")
        ax.grid(axis="y", alpha=0.3)
    axes[0][0].set_ylabel("roaming (fraction of unseen trials)")
    axes[0][0].set_ylim(-0.02, 1.02)
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--strategies", nargs="+", choices=STRATEGIES, default=list(STRATEGIES))
    parser.add_argument("--seeds", type=int, default=None, help="run seeds 0..N-1 (10)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes")
    parser.add_argument("--out", type=Path, default=None, help="champions' dir (a temp dir)")
    parser.add_argument("--reuse", action="store_true", help="explore champions found in --out")
    parser.add_argument("--generations", type=int, default=None, help="(the default run's)")
    parser.add_argument("--poses", type=int, default=None, help="unseen start poses (1000)")
    parser.add_argument("--steps", type=int, default=None, help="steps of each trial (1000)")
    parser.add_argument("--mazes", nargs="+", default=list(GENERATED_MAZES))
    parser.add_argument("--png", type=Path, default=None, help="(docs/img/; --quick: in --out)")
    parser.add_argument("--quick", action="store_true", help="2 seeds, 20 generations, 100 x 200")
    args = parser.parse_args()
    if TRAINING_MAZE in args.mazes:
        parser.error(f"--mazes are mazes never used in training: not {TRAINING_MAZE!r}")
    seeds = args.seeds if args.seeds is not None else 2 if args.quick else 10
    generations = args.generations or (20 if args.quick else RunConfig().generations)
    poses = args.poses or (100 if args.quick else 1000)
    steps = args.steps or (200 if args.quick else 1000)
    with contextlib.ExitStack() as stack:
        if args.out is None:
            out = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="strategies-")))
        else:
            out = args.out
            out.mkdir(parents=True, exist_ok=True)
        png: Path = args.png or (out / "strategies-roaming.png" if args.quick else DEFAULT_PNG)
        study(args, seeds, generations, poses, steps, out, png)


def study(
    args: argparse.Namespace,
    seeds: int,
    generations: int,
    poses: int,
    steps: int,
    out: Path,
    png: Path,
) -> None:
    """Evolve or reuse the champions, explore them, print the figures, write the png."""
    mazes = (TRAINING_MAZE, *args.mazes)
    print("mazes never used in training:")
    for spec in args.mazes:
        print(f"  {describe_maze(spec)}")
    base = RunConfig(generations=generations)
    kept = "" if args.out else " (removed at exit: pass --out to keep them)"
    print(
        f"{len(args.strategies)} strategies x {seeds} seeds, each population {base.population} x "
        f"{generations} generations of {base.trials} trials in the {base.maze!r} maze; "
        f"champions in {out}{kept}; {args.jobs} worker processes",
        flush=True,
    )

    # full CMA-ES first: its generations cost the most, so the pool ends evenly
    order = sorted(args.strategies, key=lambda s: s != "cma-es")
    tasks = [
        Task(s, seed, generations, out, args.reuse, mazes, poses, steps)
        for s in order
        for seed in range(seeds)
    ]
    explored: dict[str, dict[str, list[Exploration | None]]] = {
        s: {m: [None] * seeds for m in mazes} for s in args.strategies
    }
    began = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
        for o in pool.imap_unordered(run, tasks):
            for maze, e in o.explored.items():
                explored[o.strategy][maze][o.seed] = e
            how = "reused" if o.evolved_s is None else f"evolved in {o.evolved_s:.1f} s"
            roaming = ", ".join(f"{m} {e.roaming:.3f}" for m, e in o.explored.items())
            print(f"{o.strategy} seed {o.seed}: {how}; roaming {roaming}", flush=True)
    wall = time.perf_counter() - began

    reports = {
        s: {m: [e for e in es if e is not None] for m, es in by.items()}
        for s, by in explored.items()
    }
    samples = {
        s: {
            m: {
                "roaming": [e.roaming for e in es],
                "stuck": [e.stuck[steps] for e in es],
                "coverage": [e.coverage for e in es],
            }
            for m, es in by.items()
        }
        for s, by in reports.items()
    }
    print()
    print(
        f"champions over {poses} unseen start poses x {steps} steps (exploration stream, seed "
        f"{TEST_SEED}); median [bootstrap 95 % CI] over {seeds} seeds; wall {wall:.0f} s"
    )
    medians: dict[str, dict[str, dict[str, float]]] = {m: {} for m in mazes}
    print(
        f"{'maze':9s} {'strategy':11s} {'roaming':>22s} {f'stuck by {steps}':>22s} {'coverage':>20s}"
    )
    for maze in mazes:
        for s in args.strategies:
            summaries = {k: summarize(v) for k, v in samples[s][maze].items()}
            medians[maze][s] = {k: v.median for k, v in summaries.items()}
            print(
                f"{maze:9s} {s:11s} {cell(summaries['roaming']):>22s} "
                f"{cell(summaries['stuck']):>22s} {summaries['coverage'].median:8.1f} "
                f"[{summaries['coverage'].ci_low:.1f}, {summaries['coverage'].ci_high:.1f}]"
            )

    for maze in mazes:
        comparisons = compare(
            {s: {k: samples[s][maze][k] for k in COMPARED} for s in args.strategies}
        )
        print()
        print(f"{maze}: Mann-Whitney U, Holm over this maze's {len(comparisons)} comparisons")
        for c in comparisons:
            print(
                f"  {c.a:>11s} vs {c.b:11s} {c.metric:8s} p {c.p_value:.3g}, p_holm {c.p_holm:.3g}, A12 {c.a12:.2f}"
            )
        for line in verdicts(comparisons) or ["(fewer than 2 seeds: nothing to compare)"]:
            print(f"  {line}")

    print()
    best = best_strategy(medians[TRAINING_MAZE])
    print(f"targets (issue 26) for the best strategy by median roaming in {TRAINING_MAZE}: {best}")
    held = [
        target(f"{maze} {metric}", medians[maze][best][metric], bound, at_least)
        for maze, metric, bound, at_least in (
            (TRAINING_MAZE, "roaming", TARGET_ROAMING, True),
            (TRAINING_MAZE, "stuck", TARGET_STUCK, False),
            *((m, "roaming", TARGET_GENERATED, True) for m in args.mazes),
        )
    ]
    print(f"targets hold: {'yes' if all(held) else 'no'}")
    plot({s: {m: samples[s][m]["roaming"] for m in mazes} for s in args.strategies}, mazes, png)
    print(f"box plots of roaming: {png}")


if __name__ == "__main__":
    main()
