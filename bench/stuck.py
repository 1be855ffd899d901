"""Precision and recall of robot_agent.stuck against simulated traces whose truth is known.

Robots run in lockstep with the simulator's sensing, motion and collision (`evorobotics.sim`,
blocked moves refused, as robot_agent.sim_body does), reality gap on, under two kinds of
controller: random networks (paper-best preset, weights uniform in [-1, 1]) and evolved-like
ones (drive forward; on contact back up, then turn away for a random time; some never back up).
Then the champions of `--champions` default runs (`colony evolve --seed S`, S = 0..N-1), each
on `--robots` / N robots, in the nominal world and under the gap, as the agent uses the
detector: an alarm resets it (a new controller would start afresh), and the alarms are counted
per robot-hour, false ones (the robot was not stuck) apart.
Truth at step t (from positions the robot itself cannot see): in the last `--window` steps
the robot stayed within `--radius` m of where it was at the window's start, i.e. it is pinned,
spinning or rocking in place. Steps before the first full window are not scored.

    .venv/bin/python bench/stuck.py [--robots 200] [--steps 600] [--maze paper] [--seed 0]
        [--champions 10] [--champion-steps 3000]
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

import numpy as np

from evorobotics import network
from evorobotics.evaluate import draw_gap, start_poses
from evorobotics.evolution import evolve
from evorobotics.maze import Maze, load_maze
from evorobotics.seeds import Purpose, rng
from evorobotics.sim import Gap, body_hits_wall, move, whisker_bits
from robot_agent.stuck import StuckConfig, StuckDetector, detect
from schemas.network import PRESETS, NetworkSpec
from schemas.run import RunConfig
from schemas.world import World


def evolved_like(whiskers: np.ndarray, memory: np.ndarray, traits: np.ndarray) -> np.ndarray:
    """Reactive controllers with a short memory; memory (B, 2): back-up and turn counters."""
    batch = whiskers.shape[0]
    motors = np.tile(traits[:, 0:1], (1, 2))  # cruise speed
    touch = whiskers.any(axis=1)
    left_side = whiskers[:, :2].any(axis=1)
    start = touch & (memory[:, 0] == 0) & (memory[:, 1] == 0)
    memory[start, 0] = traits[start, 1]  # back-up steps (0: a controller that never backs up)
    memory[start, 1] = traits[start, 1] + traits[start, 2]  # then turn steps
    direction = np.where(left_side, -1.0, 1.0)
    backing = memory[:, 0] > 0
    turning = ~backing & (memory[:, 1] > 0)
    motors[backing] = -0.6
    turn = direction[turning]
    motors[turning, 0] = -0.5 * turn
    motors[turning, 1] = 0.5 * turn
    memory[:, 0] = np.maximum(memory[:, 0] - 1, 0)
    memory[:, 1] = np.maximum(memory[:, 1] - 1, 0)
    del batch
    return motors


Control = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""Motors (B, 2) from the step's whisker bits (B, 5) and the poses (B, 3) they were sensed at
(what an overhead tracker sees; a controller ignores them)."""
"""A batch's controller step: whisker bits (B, 5) in, wheel commands (B, 2) out."""


def lockstep(
    maze: Maze, poses: np.ndarray, gap: Gap, steps: int, control: Control
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robots stepped with the simulator's sensing, motion and collision (a move into a wall
    is refused): poses (B, T + 1, 3), each step's sensed at and the last, whiskers (B, T, 5)
    and motors (B, T, 2)."""
    params = World()
    pose = poses.copy()  # a cached draw is read-only
    robots = pose.shape[0]
    p_all = np.zeros((robots, steps + 1, 3))
    w_all = np.zeros((robots, steps, 5), dtype=np.uint8)
    m_all = np.zeros((robots, steps, 2))
    p_all[:, 0] = pose
    for t in range(steps):
        bits = whisker_bits(maze, pose, params, gap.whisker_range)
        motors = control(bits, pose)
        moved = move(pose, motors, gap.motor_gain, params)
        ok = ~body_hits_wall(maze, moved, params)
        pose[ok] = moved[ok]
        w_all[:, t], m_all[:, t], p_all[:, t + 1] = bits, motors, pose
    return p_all, w_all, m_all


def network_control(spec: NetworkSpec, weights: np.ndarray) -> Control:
    """Networks of `weights` (B, n) stepping on the bits, from fresh state."""
    state = network.reset(spec, weights.shape[0])

    def control(bits: np.ndarray, _pose: np.ndarray) -> np.ndarray:
        nonlocal state
        out, state = network.step(spec, weights, bits.astype(np.float64), state)
        return network.motor_commands(spec, out)

    return control


def traces(
    maze_name: str, robots: int, steps: int, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whiskers (B, T, 5), motors (B, T, 2), positions (B, T + 1, 2); half random, half evolved-like."""
    maze = load_maze(maze_name)
    poses = start_poses(maze, seed, 0, robots, World())
    spec = PRESETS["paper-best"]
    n_random = robots // 2
    gen = rng(seed, 0, Purpose.EVALUATION, 0)
    randoms = network_control(spec, gen.uniform(-1.0, 1.0, (n_random, spec.weight_count)))
    traits = np.column_stack(
        [
            gen.uniform(0.3, 1.0, robots - n_random),
            gen.integers(0, 6, robots - n_random),
            gen.integers(2, 15, robots - n_random),
        ]
    )
    memory = np.zeros((robots - n_random, 2))

    def control(bits: np.ndarray, pose: np.ndarray) -> np.ndarray:
        motors = np.empty((robots, 2))
        motors[:n_random] = randoms(bits[:n_random], pose[:n_random])
        motors[n_random:] = evolved_like(bits[n_random:], memory, traits)
        return motors

    p, w, m = lockstep(maze, poses, draw_gap(seed, 0, robots), steps, control)
    return w, m, p[:, :, :2]


def champion_traces(
    maze_name: str, weights: np.ndarray, steps: int, seed: int, gap_on: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Traces of evolved champions (B, weights): whiskers, motors, positions as `traces`."""
    maze = load_maze(maze_name)
    robots = weights.shape[0]
    poses = start_poses(maze, seed, 1, robots, World())
    gap = draw_gap(seed, 1, robots) if gap_on else Gap.nominal(robots, World())
    control = network_control(PRESETS["paper-best"], weights)
    p, w, m = lockstep(maze, poses, gap, steps, control)
    return w, m, p[:, :, :2]


def alarms(
    whiskers: np.ndarray, motors: np.ndarray, cfg: StuckConfig, poses: np.ndarray | None = None
) -> list[int]:
    """Steps at which the agent would raise a stuck alarm (with a tracker's `poses` (T, 2), if
    given); each alarm resets the detector."""
    detector = StuckDetector(cfg)
    out = []
    for t in range(whiskers.shape[0]):
        pose = None if poses is None else poses[t]
        if detector.update(tuple(bool(b) for b in whiskers[t]), motors[t], pose) is not None:
            out.append(t)
            detector.reset()
    return out


def field_figures(
    label: str,
    w: np.ndarray,
    m: np.ndarray,
    real: np.ndarray,
    window: int,
    xy: np.ndarray | None = None,
) -> None:
    """Alarms per robot-hour, false ones apart, and the share of truly stuck robots alarmed;
    with `xy` (B, T+1, 2) the detector also has a tracker's poses (where each step sensed)."""
    cfg = StuckConfig()
    true_alarms = false_alarms = 0
    caught = stuck_robots = 0
    for b in range(w.shape[0]):
        tracked = None if xy is None else xy[b, :-1]
        # an alarm at step t is scored on the 40 steps up to the pose the robot sensed at t
        # (truth[t - 1]): truth[t] ends with step t's own move, which nothing sensed yet
        fired = [t for t in alarms(w[b], m[b], cfg, tracked) if t > window]
        hits = [t for t in fired if real[b, t - 1]]
        true_alarms += len(hits)
        false_alarms += len(fired) - len(hits)
        if real[b, window:].any():
            stuck_robots += 1
            caught += bool(hits)
    hours = w.shape[0] * w.shape[1] * World().dt / 3600.0
    print(
        f"{label:30s} alarms/robot-hour {((true_alarms + false_alarms) / hours):7.1f}, "
        f"false {false_alarms / hours:7.1f} ({false_alarms} of {true_alarms + false_alarms}); "
        f"robots ever stuck {stuck_robots}/{w.shape[0]}, alarmed while stuck {caught}"
    )


def truth(xy: np.ndarray, window: int, radius: float) -> np.ndarray:
    """(B, T) bool: stayed within `radius` of the window-start position for `window` steps."""
    robots, n = xy.shape[0], xy.shape[1] - 1
    out = np.zeros((robots, n), dtype=bool)
    for t in range(window, n):
        span = xy[:, t + 1 - window : t + 2]
        out[:, t] = (np.linalg.norm(span - span[:, :1], axis=-1) < radius).all(axis=1)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--robots", type=int, default=200)
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--maze", default="paper")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--window", type=int, default=40, help="truth window, steps (4 s)")
    parser.add_argument("--radius", type=float, default=0.1, help="truth radius, m")
    parser.add_argument("--champions", type=int, default=10, help="default runs' champions")
    parser.add_argument("--champion-steps", type=int, default=3000, help="steps of their traces")
    args = parser.parse_args()
    w, m, xy = traces(args.maze, args.robots, args.steps, args.seed)
    real = truth(xy, args.window, args.radius)
    cfg = StuckConfig()
    flags = np.array([[r is not None for r in detect(w[b], m[b], cfg)] for b in range(args.robots)])
    reasons: dict[str, int] = {}
    for b in range(args.robots):
        for r in detect(w[b], m[b], cfg):
            if r is not None:
                reasons[r.value] = reasons.get(r.value, 0) + 1
    scored = np.zeros_like(real)
    scored[:, args.window :] = True
    half = args.robots // 2
    print(f"maze={args.maze} robots={args.robots} steps={args.steps} seed={args.seed} {cfg}")
    print(f"truth: within {args.radius} m for {args.window} steps; fired by reason {reasons}")
    for name, rows in (
        ("all", slice(None)),
        ("random", slice(0, half)),
        ("evolved-like", slice(half, None)),
    ):
        f, r, s = flags[rows] & scored[rows], real[rows] & scored[rows], scored[rows]
        tp = int((f & r).sum())
        precision = tp / max(int(f.sum()), 1)
        recall = tp / max(int(r.sum()), 1)
        # per robot: ever truly stuck vs ever flagged
        ever_f, ever_r = f.any(axis=1), r.any(axis=1)
        rp = int((ever_f & ever_r).sum()) / max(int(ever_f.sum()), 1)
        rr = int((ever_f & ever_r).sum()) / max(int(ever_r.sum()), 1)
        print(
            f"{name:13s} steps: precision {precision:.3f} recall {recall:.3f} "
            f"(stuck {int(r.sum())}/{int(s.sum())})  robots: precision {rp:.3f} recall {rr:.3f} "
            f"(stuck {int(ever_r.sum())}, flagged {int(ever_f.sum())})"
        )
    if args.champions < 1:
        return
    champions = np.stack([evolve(RunConfig(seed=s)).best.weights for s in range(args.champions)])
    per = max(args.robots // args.champions, 1)
    weights = np.repeat(champions, per, axis=0)
    print(
        f"champions of seeds 0-{args.champions - 1}, {per} robots each, "
        f"{args.champion_steps} steps ({args.champion_steps * World().dt:.0f} s) in {args.maze!r}"
    )
    for gap_on in (False, True):
        w, m, xy = champion_traces(args.maze, weights, args.champion_steps, args.seed, gap_on)
        real = truth(xy, args.window, args.radius)
        label = "under the gap" if gap_on else "nominal"
        field_figures(f"champions, {label}", w, m, real, args.window)
        field_figures(f"  with a tracker, {label}", w, m, real, args.window, xy)


if __name__ == "__main__":
    main()
