"""Robot-steps per second of the Gymnasium environments under a random policy (docs/gym.md).

The vector env (`gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`, one
compiled call per step for the whole batch, next-step autoreset) against the single env
(`gymnasium.make`, resetting when an episode ends), both sampling their actions from the action
space; and the vector env's step alone (no robot ever ends an episode, so no reset, and
actions drawn beforehand). Rounds alternate A, B, C, A, B, C... so a change of machine load
hits all; prints each round's figures, the best of each, and the vector / single ratio.

    .venv/bin/python bench/gym.py [--batch 256] [--seconds 1.0] [--rounds 3] [--maze paper]
"""

from __future__ import annotations

import argparse
import time

import gymnasium
import numpy as np

import evorobotics.gym
from schemas.world import World


def single_rate(maze: str, world: World, seconds: float) -> float:
    """Steps per second of one env driven by `action_space.sample()` for `seconds`."""
    env = gymnasium.make(evorobotics.gym.ENV_ID, maze=maze, world=world)
    env.reset(seed=0)
    env.action_space.seed(0)
    steps = 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        for _ in range(100):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
        steps += 100
    return steps / (time.perf_counter() - start)


def vector_rate(maze: str, world: World, batch: int, seconds: float) -> float:
    """Robot-steps per second of the vector env of `batch` robots for `seconds`."""
    envs = gymnasium.make_vec(
        evorobotics.gym.ENV_ID,
        num_envs=batch,
        vectorization_mode="vector_entry_point",
        maze=maze,
        world=world,
    )
    envs.reset(seed=0)
    envs.action_space.seed(0)
    calls = 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        for _ in range(10):
            envs.step(envs.action_space.sample())
        calls += 10
    return calls * batch / (time.perf_counter() - start)


def step_rate(maze: str, batch: int, seconds: float) -> float:
    """Robot-steps per second of the vector env's step alone: no robot ever stuck or truncated
    (so no reset), actions drawn beforehand."""
    envs = evorobotics.gym.EvBotMazeVectorEnv(
        batch, maze=maze, world={"stuck_after": 10**6}, steps=10**9
    )
    envs.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (10, batch, 2))
    calls = 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        for a in actions:
            envs.step(a)
        calls += len(actions)
    return calls * batch / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--seconds", type=float, default=1.0, help="timed per round and env")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--maze", default="paper")
    args = parser.parse_args()
    world = World()
    single_rate(args.maze, world, 0.05)  # warm-up: kernel load, first reset
    vector_rate(args.maze, world, args.batch, 0.05)
    step_rate(args.maze, args.batch, 0.05)
    singles, vectors, steps_only = [], [], []
    for r in range(args.rounds):
        singles.append(single_rate(args.maze, world, args.seconds))
        vectors.append(vector_rate(args.maze, world, args.batch, args.seconds))
        steps_only.append(step_rate(args.maze, args.batch, args.seconds))
        print(
            f"round {r + 1}: single env {singles[-1]:,.0f} steps/s, "
            f"vector env (batch {args.batch}) {vectors[-1]:,.0f} robot-steps/s, "
            f"its step alone {steps_only[-1]:,.0f} robot-steps/s"
        )
    best_single, best_vector = max(singles), max(vectors)
    print(f"best single env: {best_single:,.0f} steps/s")
    print(f"best vector env (batch {args.batch}): {best_vector:,.0f} robot-steps/s")
    print(f"best vector env step alone: {max(steps_only):,.0f} robot-steps/s")
    print(f"vector / single: {best_vector / best_single:.1f}x")


if __name__ == "__main__":
    main()
