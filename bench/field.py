"""The field loop's figures: calibration from traces, false stuck alarms per robot-hour, and
what calibrate-then-`fit` does to a colony's stuck events.

Emulated robots run as the agent runs them (robot_agent.agent): the controller at every step,
the agent's stuck detector (`StuckConfig()`), and on an alarm its scripted escape (8 steps
back, 6 turning) before the same controller resumes from fresh state; moves into a wall are
refused, as robot_agent.sim_body does. The controller is the default run's champion
(`colony evolve`, seed 0), the maze the paper's.

- Calibration: `--robots` (10) robots, each with hidden physics drawn from the paper's gap
  (`SimBody.create("paper", seed=--seed, index=i)`: each whisker 25-100 mm, each wheel +-15 %),
  traced for each of `--horizons` steps (1,200 = 120 s, the target's; 6,000 = 10 min), then
  `evorobotics.calibrate.calibrate` on the traces' true poses. Prints per robot the largest
  whisker-range and wheel-gain errors, and how many robots are within 3 mm and 0.02
  (the target: 9 of 10 at 1,200 steps).
- False alarms: 8 robots in the nominal world for `--hours` (1) hour each: alarms per
  robot-hour, and those raised while the robot was not stuck: its controller moved it more
  than 0.1 m in the 40 steps before, counted from where it last resumed after an escape (the
  escape's own backing and turning is the agent's move, not the robot getting anywhere).
  Target: at most 1. The figure that counts the escape's moves too is printed beside it. Then
  the same with a tracker: the detector is given each step's true position.
- The loop pays (`loop_pays`): per seed, 8 robots with hidden gap physics run the champion
  pushed blind for `--minutes` (10), then the `fit` choice after calibrating from those traces.
  Stuck events per robot-hour before and after, their ratio over `--seeds` (30: one robot
  trapped in a loop can dominate a seed, so ten seeds cannot tell the arms apart) with a
  bootstrap CI over seeds, and the same for the champion of a run trained for the colony
  (`reality_gap: "colony"` on the 8 calibrations, `colony run start --for-colony`). Target: at
  most 1/5.

    .venv/bin/python bench/field.py [--robots 10] [--horizons 1200 6000] [--hours 1] [--seed 3]
        [--seeds 30] [--minutes 10] [--candidates 100] [--figure docs/img/field-loop.png]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from stuck import lockstep

from evorobotics import network
from evorobotics.calibrate import CalibrationError, calibrate
from evorobotics.evaluate import available_cores
from evorobotics.evolution import evolve, rank_in_world
from evorobotics.ga import rank
from evorobotics.maze import load_maze
from evorobotics.sim import Gap
from evorobotics.stats import a12
from robot_agent.agent import AgentSettings
from robot_agent.sim_body import SimBody
from robot_agent.stuck import StuckDetector
from schemas.network import NetworkSpec
from schemas.robots import RobotCalibration
from schemas.run import RunConfig
from schemas.world import World

TRUTH_STEPS = 40
TRUTH_RADIUS = 0.1


def run_colony(
    spec: NetworkSpec,
    weights: np.ndarray,
    poses: np.ndarray,
    gap: Gap,
    steps: int,
    *,
    tracker: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[list[int]]]:
    """Robots (B,) under the agent's loop, running `weights` (n,) or each its own (B, n), the
    detector given each step's true position with `tracker` (an overhead tracker's): poses
    (B, T, 3) sensed at, whiskers (B, T, 5), motors (B, T, 2), each robot's alarm steps."""
    agent = AgentSettings(robot_id="bench")
    escape = [(-agent.escape_speed, -agent.escape_speed)] * agent.escape_back_steps + [
        (agent.escape_speed, -agent.escape_speed)
    ] * agent.escape_turn_steps
    b = poses.shape[0]
    w = weights if weights.ndim == 2 else np.repeat(weights[None], b, axis=0)
    state = network.reset(spec, b)
    detectors = [StuckDetector(agent.stuck) for _ in range(b)]
    plans: list[list[tuple[float, float]]] = [[] for _ in range(b)]
    alarms: list[list[int]] = [[] for _ in range(b)]
    step = 0

    def control(bits: np.ndarray, pose: np.ndarray) -> np.ndarray:
        nonlocal state, step
        out, state = network.step(spec, w, bits.astype(np.float64), state)
        motors = network.motor_commands(spec, out)
        for i in range(b):
            if plans[i]:
                motors[i] = plans[i].pop(0)
                if not plans[i]:  # the controller resumes from fresh state
                    state[i] = 0.0
                    detectors[i].reset()
            elif (
                detectors[i].update(
                    [bool(x) for x in bits[i]], motors[i], tuple(pose[i, :2]) if tracker else None
                )
                is not None
            ):
                alarms[i].append(step)
                plans[i] = list(escape)
        step += 1
        return motors

    p, whiskers, motors = lockstep(load_maze("paper"), poses, gap, steps, control)
    return p[:, :-1], whiskers, motors, alarms


def hidden_colony(seed: int, robots: int) -> tuple[np.ndarray, Gap]:
    """Start poses (robots, 3) and hidden gap physics of `SimBody.create("paper", seed, i)`."""
    bodies = [SimBody.create("paper", seed=seed, index=i) for i in range(robots)]
    gap = Gap(
        np.concatenate([np.broadcast_to(x.gap.whisker_range, (1, 5)) for x in bodies]),
        np.concatenate([x.gap.motor_gain for x in bodies]),
    )
    return np.stack([np.asarray(x.pose, dtype=np.float64).reshape(3) for x in bodies]), gap


Fitted = tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, ...]]
"""One robot's hidden whisker ranges (5,), fitted ranges (5,), their half-widths (5,), and the
whiskers known only within an interval."""


def calibration(
    spec: NetworkSpec, weights: np.ndarray, robots: int, horizon: int, seed: int
) -> list[Fitted]:
    poses, gap = hidden_colony(seed, robots)
    began = time.perf_counter()
    p, w, m, _ = run_colony(spec, weights, poses, gap, horizon)
    traced = time.perf_counter() - began
    maze, world = load_maze("paper"), World()
    within = bounded = strict = 0
    fitted: list[Fitted] = []
    print(f"calibration from {horizon} steps ({horizon * world.dt:.0f} s) of traces per robot:")
    for i in range(robots):
        try:
            fit = calibrate(maze, p[i], w[i], m[i], world)
        except CalibrationError as exc:
            print(f"  robot {i}: not calibrated: {exc}")
            continue
        changed = [k for k in range(5) if k not in fit.bounded]
        errors = np.abs(np.array(fit.whisker_range) - gap.whisker_range[i])
        r_err = float(errors[changed].max(initial=0.0))
        g_err = float(np.abs(np.array(fit.motor_gain) - gap.motor_gain[i]).max())
        half = np.array(fit.whisker_range_uncertainty)
        fitted.append((gap.whisker_range[i], np.array(fit.whisker_range), half, fit.bounded))
        inside = all(errors[k] <= half[k] + 1e-9 for k in fit.bounded)
        ok = r_err <= 0.003 and g_err <= 0.02 and inside
        within += ok
        bounded += bool(fit.bounded)
        strict += ok and not fit.bounded
        hidden = ", ".join(f"{1000 * r:.0f}" for r in gap.whisker_range[i])
        low = 1000 * (np.array(fit.whisker_range) - half)
        high = 1000 * (np.array(fit.whisker_range) + half)
        below = "".join(f"; whisker {k} in [{low[k]:.0f}, {high[k]:.0f}] mm" for k in fit.bounded)
        print(
            f"  robot {i}: hidden whiskers [{hidden}] mm, gains {gap.motor_gain[i].round(3)}; "
            f"largest error {1000 * r_err:.2f} mm and {g_err:.2e}{below}"
            f"{'' if ok else '  (outside the target)'}"
        )
    print(
        f"  within 3 mm and 0.02 (a whisker whose bit never changed: hidden within its "
        f"interval): {within} of {robots} robots (target 9 of 10), {bounded} with such a "
        f"whisker; every whisker within 3 mm: {strict} of {robots}; "
        f"{traced:.1f} s to trace"
    )
    return fitted


def false_alarms(
    spec: NetworkSpec, weights: np.ndarray, hours: float, seed: int, *, tracker: bool
) -> None:
    world = World()
    steps = round(hours * 3600 / world.dt)
    bodies = [SimBody.create("paper", seed=seed, index=i, gap=False) for i in range(8)]
    poses = np.stack([np.asarray(x.pose, dtype=np.float64).reshape(3) for x in bodies])
    gap = Gap.nominal(8, world)
    p, _, _, alarms = run_colony(spec, weights, poses, gap, steps, tracker=tracker)
    agent = AgentSettings(robot_id="bench")
    escape = agent.escape_back_steps + agent.escape_turn_steps
    false = with_escapes = total = 0
    for i, fired in enumerate(alarms):
        resumed = 0  # the step its controller drives from: the start, or after an escape
        for t in fired:
            total += 1
            for start, counts_escape in ((max(t - TRUTH_STEPS, resumed), False),
                                         (max(t - TRUTH_STEPS, 0), True)):  # fmt: skip
                track = p[i, start : t + 1, :2] - p[i, start, :2]
                moved = bool(np.linalg.norm(track, axis=1).max() > TRUTH_RADIUS)
                with_escapes += moved and counts_escape
                false += moved and not counts_escape
            resumed = t + escape + 1
    robot_hours = 8 * steps * world.dt / 3600
    print(
        f"nominal colony{', with a tracker' if tracker else ''}, 8 robots x {hours:g} h: "
        f"{total / robot_hours:.1f} alarms per "
        f"robot-hour, {false / robot_hours:.2f} false ({false} of {total}; target <= 1), "
        f"{with_escapes / robot_hours:.2f} ({with_escapes}) if the previous escape's own "
        "moves counted as the robot moving"
    )


def loop_pays(seeds: int, minutes: float, candidates: int, threads: int) -> dict[str, list[float]]:
    """Per seed S: the champion of `colony evolve --seed S` on 8 robots with hidden physics
    (`SimBody.create("paper", seed=100 + S, index=i)`) for `minutes` each, pushed blind; then
    each robot calibrated from those traces and given the `fit` choice among the run's
    `candidates` fittest (`evolution.rank_in_world` in its calibrated world, as the
    server ranks them), run again from the same start poses. A robot whose traces do not
    calibrate keeps the champion (the server refuses `push --fit` for it). Replacement is off
    in both: the figures are the pushed controllers' own stuck rates."""
    world = World()
    steps = round(minutes * 60 / world.dt)
    maze = load_maze("paper")
    blind_rates, fit_rates, colony_rates = [], [], []
    print(f"the loop pays: 8 robots x {minutes:g} min per seed, blind champion, then fit:")
    for seed in range(seeds):
        config = RunConfig(seed=seed)
        result = evolve(config, threads=threads)
        spec, champion = result.best.spec, result.best.weights
        top = result.genomes[rank(result.fitness)[:candidates]]
        poses, gap = hidden_colony(100 + seed, 8)
        p, w, m, blind = run_colony(spec, champion, poses, gap, steps)
        picks, kept, robots = [], 0, []
        for i in range(8):
            try:
                fit = calibrate(maze, p[i], w[i], m[i], world)
            except CalibrationError:
                picks.append(champion)
                kept += 1
                continue
            stored = RobotCalibration.model_validate(fit.as_dict())
            robots.append(stored.gap_robot(f"robot-{i}"))
            order, _ = rank_in_world(config, top, stored.world(world), threads=threads)
            picks.append(top[order[0]])
        _, _, _, after = run_colony(spec, np.stack(picks), poses, gap, steps)
        ours = blind  # no robot calibrated: the server refuses --for-colony, nothing changes
        if robots:  # what `colony run start --for-colony` trains on
            colony = RunConfig(
                seed=seed, reality_gap="colony", world=World(gap_robots=tuple(robots))
            )
            trained = evolve(colony, threads=threads).best
            _, _, _, ours = run_colony(spec, trained.weights, poses, gap, steps)
        hours = 8 * steps * world.dt / 3600
        blind_rates.append(sum(map(len, blind)) / hours)
        fit_rates.append(sum(map(len, after)) / hours)
        colony_rates.append(sum(map(len, ours)) / hours)
        print(
            f"  seed {seed}: {blind_rates[-1]:6.1f} -> fit {fit_rates[-1]:6.1f}, for-colony "
            f"{colony_rates[-1]:6.1f} stuck events per robot-hour (per robot "
            f"{[len(a) for a in blind]} -> {[len(a) for a in after]}, {[len(a) for a in ours]}; "
            f"{kept} not calibrated, kept the champion)"
        )
    b = np.array(blind_rates)
    boot = np.random.default_rng(0).integers(0, len(b), (2000, len(b)))
    for label, rates in (("fit", fit_rates), ("for-colony", colony_rates)):
        f = np.array(rates)
        low, high = np.quantile(
            f[boot].sum(axis=1) / np.maximum(b[boot].sum(axis=1), 1e-9), [0.025, 0.975]
        )
        print(
            f"  {label} over {seeds} seeds: {b.mean():.1f} -> {f.mean():.1f} per robot-hour, "
            f"ratio {f.sum() / b.sum():.2f} (95 % bootstrap CI {low:.2f}-{high:.2f}; target "
            f"<= 0.20); better on {int((f < b).sum())}, worse on {int((f > b).sum())} seeds; "
            f"A12 {a12(blind_rates, rates):.2f}"
        )
    return {"blind": blind_rates, "fit": fit_rates, "for-colony": colony_rates}


def figure(path: str, fitted: list[Fitted], rates: dict[str, list[float]]) -> None:
    """docs/robots.md's figure: hidden against fitted whisker ranges, and each seed's stuck
    events per robot-hour pushed blind, after `fit`, and trained for the colony."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.6))
    for hidden, fit, half, bounded in fitted:
        exact = [k for k in range(5) if k not in bounded]
        left.plot(1000 * hidden[exact], 1000 * fit[exact], "o", color="tab:blue", ms=5)
        for k in bounded:
            left.errorbar(
                1000 * hidden[k], 1000 * fit[k], yerr=1000 * half[k], fmt="s", color="tab:orange",
                ms=4, capsize=3,
            )  # fmt: skip
    left.plot([20, 105], [20, 105], color="0.6", lw=1, zorder=0)
    left.plot([], [], "o", color="tab:blue", label="fitted range")
    left.errorbar([], [], yerr=[], fmt="s", color="tab:orange", label="bit never changed: interval")
    left.set(
        xlabel="hidden whisker range (mm)", ylabel="fitted (mm)", xlim=(20, 105), ylim=(0, 260),
        title=f"{len(fitted)} robots, 10 min of traces each",
    )  # fmt: skip
    left.legend(loc="upper left")
    arms = list(rates)
    for s in range(len(rates["blind"])):
        right.plot(range(len(arms)), [rates[a][s] for a in arms], "-o", color="0.6", lw=1, ms=4)
    means = [float(np.mean(rates[a])) for a in arms]
    right.plot(range(len(arms)), means, "-D", color="tab:red", lw=2, label="mean over seeds")
    right.set_xticks(range(len(arms)), ["champion, blind", "calibrate, fit", "trained for colony"])
    right.set(ylabel="stuck events per robot-hour", title="8 robots x 10 min, per seed")
    right.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"figure written to {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=10)
    parser.add_argument("--horizons", type=int, nargs="+", default=[1200, 6000])
    parser.add_argument("--hours", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--seeds", type=int, default=30, help="runs for the loop-pays figure")
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument(
        "--candidates", type=int, default=RunConfig().validation.candidates, help="fit among"
    )
    parser.add_argument("--figure", help="also draw docs/robots.md's figure (a PNG path)")
    args = parser.parse_args()
    champion = evolve(RunConfig()).best
    print(f"the default run's champion {champion.sha256[:12]}, maze 'paper'")
    fitted: list[Fitted] = []
    for horizon in args.horizons:
        fitted = calibration(champion.spec, champion.weights, args.robots, horizon, args.seed)
    for tracker in (False, True):
        false_alarms(champion.spec, champion.weights, args.hours, args.seed, tracker=tracker)
    rates = loop_pays(args.seeds, args.minutes, args.candidates, available_cores())
    if args.figure:
        figure(args.figure, fitted, rates)


if __name__ == "__main__":
    main()
