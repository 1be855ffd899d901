"""The Gymnasium environments (evorobotics.gym): the API checker, agreement with the
simulator's own trials and between the single and the vector env, determinism per seed, the
docs' examples and the bench."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
from gymnasium.error import ResetNeeded
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from gymnasium.wrappers.vector import RecordEpisodeStatistics
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics import network
from evorobotics.errors import MazeError
from evorobotics.evaluate import start_poses
from evorobotics.fitness import fitness
from evorobotics.gym import ENV_ID, EvBotMazeEnv, EvBotMazeVectorEnv
from evorobotics.maze import load_maze
from evorobotics.sim import simulate
from schemas.network import PRESETS
from schemas.run import FitnessWeights
from schemas.world import World

ROOT = Path(__file__).resolve().parents[1]


def random_actions(seed: int, n: int, shape: tuple[int, ...]) -> np.ndarray:
    """n float64 actions in [-1, 1] (a quarter of them pushed beyond, to exercise the clip)."""
    gen = np.random.default_rng(seed)
    return gen.uniform(-1.25, 1.25, (n, *shape))


@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_check_env_passes(render_mode: str | None) -> None:
    env = gymnasium.make(ENV_ID, maze="gen:3:0", render_mode=render_mode)
    check_env(env.unwrapped)  # the env itself, its spec set by make (for the render checks)


def test_registered_with_options(tmp_path: Path) -> None:
    path = tmp_path / "room.txt"
    path.write_text(load_maze("corridor").text(), encoding="utf-8")
    env = gymnasium.make(ENV_ID, maze=str(path), world={"stuck_after": 3}, steps=7)
    inner = env.unwrapped
    assert isinstance(inner, EvBotMazeEnv)
    assert inner.steps == 7
    obs, info = env.reset(seed=4)
    assert env.observation_space.contains(obs)
    for k in range(7):
        obs, _, terminated, truncated, info = env.step(np.zeros(2, np.float32))
        assert not terminated
        assert truncated == (k == 6)
    assert (info["components"] == 0).all()  # standing still scores nothing
    envs = gymnasium.make_vec(ENV_ID, num_envs=3, vectorization_mode="vector_entry_point")
    assert isinstance(envs.unwrapped, EvBotMazeVectorEnv)
    assert envs.unwrapped.steps == 240  # three crossings of the paper maze


def test_bad_options_are_refused_with_the_problem_named() -> None:
    with pytest.raises(ValueError, match="stuck_after"):
        EvBotMazeEnv(world={"stuck_after": 0})
    with pytest.raises(ValueError, match="k9"):
        EvBotMazeEnv(fitness={"k9": 1.0})
    with pytest.raises(ValueError, match="steps"):
        EvBotMazeEnv(steps=0)
    with pytest.raises(MazeError, match="unknown maze"):
        EvBotMazeEnv(maze="no-such-maze")
    with pytest.raises(ValueError, match="render_mode"):
        EvBotMazeEnv(render_mode="human")
    with pytest.raises(ValueError, match="num_envs"):
        EvBotMazeVectorEnv(0)
    env = EvBotMazeEnv(maze="arena")
    with pytest.raises(ResetNeeded):
        env.step(np.zeros(2))
    with pytest.raises(ResetNeeded):
        EvBotMazeVectorEnv(2).step(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="in a wall"):
        env.reset(options={"pose": (0.0, 0.0, 0.0)})
    for bad in [(1.0, float("nan"), 0.0), (1.0, 1.0), "north", {"x": 1}]:
        with pytest.raises(ValueError, match="finite"):
            env.reset(options={"pose": bad})
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        env.step(np.zeros(3))
    envs = EvBotMazeVectorEnv(2, maze="arena")
    envs.reset(seed=0)
    with pytest.raises(ValueError, match=r"\(2, 2\)"):
        envs.step(np.zeros(2))


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    stuck_after=st.sampled_from([1, 3]),
    dt=st.floats(0.05, 0.2),
    max_speed=st.floats(0.1, 0.8),
    whisker_range=st.floats(0.02, 0.1),
)
def test_driving_the_env_with_a_trials_motors_retraces_the_trial(
    seed: int, stuck_after: int, dt: float, max_speed: float, whisker_range: float
) -> None:
    """The same world, pose and wheel commands as `simulate`'s trial: the same poses and
    whisker bits bit for bit, terminated on the step the trial gets stuck, Eq 12 terms equal,
    and the rewards summing to Eq 12's fitness."""
    spec = PRESETS["paper-best"]
    world = World(stuck_after=stuck_after, dt=dt, max_speed=max_speed, whisker_range=whisker_range)
    weights = FitnessWeights(k1=0.5)
    maze = load_maze("paper")
    steps = 60
    pose = start_poses(maze, seed, 0, 1, world)
    genome = np.random.default_rng(seed).normal(0.0, 1.5, (1, spec.weight_count))
    trial = simulate(spec, genome, maze, pose, steps, world, record=True)
    assert trial.poses is not None and trial.whiskers is not None and trial.motors is not None
    env = EvBotMazeEnv(maze="paper", world=world, steps=steps, fitness=weights)
    obs, _ = env.reset(seed=seed, options={"pose": pose[0]})
    assert (obs == trial.whiskers[0, 0]).all()
    total = 0.0
    for k in range(steps):
        obs, reward, terminated, truncated, info = env.step(trial.motors[0, k])
        total += float(reward)
        assert (info["pose"] == trial.poses[0, k + 1]).all()
        if k + 1 < steps:
            assert (obs == trial.whiskers[0, k + 1]).all()
        assert terminated == (trial.stuck_step[0] == k + 1)
        assert truncated == (k + 1 == steps)
        if terminated or truncated:
            break
    assert (info["components"] == trial.components[0]).all()
    assert total == pytest.approx(float(fitness(trial.components, weights)[0]), abs=1e-9)


def test_a_network_driving_the_env_scores_its_simulated_trial() -> None:
    """The docs' controller loop (network.step on the observations) ends with the Eq 12 terms
    of `simulate`'s trial of the same network from the same pose, its return their fitness."""
    spec = PRESETS["paper-best"]
    maze, steps = load_maze("gen:4:0"), 120
    pose = start_poses(maze, 2, 0, 1)
    for seed in range(4):
        weights = np.random.default_rng(seed).normal(0.0, 1.5, (1, spec.weight_count))
        trial = simulate(spec, weights, maze, pose, steps)
        env = EvBotMazeEnv(maze="gen:4:0", steps=steps)
        obs, _ = env.reset(options={"pose": pose[0]})
        state = network.reset(spec, 1)
        total, done = 0.0, False
        while not done:
            out, state = network.step(spec, weights, obs[None].astype(np.float64), state)
            obs, reward, terminated, truncated, info = env.step(
                network.motor_commands(spec, out)[0]
            )
            total += float(reward)
            done = terminated or truncated
        assert (info["components"] == trial.components[0]).all()
        expected = float(fitness(trial.components, FitnessWeights())[0])
        assert total == pytest.approx(expected, abs=1e-9)


def test_vector_env_retraces_a_batch_of_trials() -> None:
    """Eight robots from `simulate`'s poses on its recorded motor commands: each row follows
    its trial bit for bit until its episode ends."""
    spec = PRESETS["paper-best"]
    maze, steps, n = load_maze("paper"), 50, 8
    poses = start_poses(maze, 7, 0, n)
    genomes = np.random.default_rng(7).normal(0.0, 1.5, (n, spec.weight_count))
    trial = simulate(spec, genomes, maze, poses, steps, record=True)
    assert trial.poses is not None and trial.whiskers is not None and trial.motors is not None
    envs = EvBotMazeVectorEnv(n, steps=steps)
    obs, _ = envs.reset(seed=0, options={"pose": poses})
    assert (obs == trial.whiskers[:, 0]).all()
    live = np.ones(n, dtype=np.bool_)
    for k in range(steps):
        obs, _, terminated, truncated, info = envs.step(trial.motors[:, k])
        assert (info["pose"][live] == trial.poses[live, k + 1]).all()
        if k + 1 < steps:
            assert (obs[live] == trial.whiskers[live, k + 1]).all()
        ended = live & (terminated | truncated)
        assert (info["components"][ended] == trial.components[ended]).all()
        live &= ~ended
    assert not live.any()


def run_single(env: EvBotMazeEnv, seed: int, actions: np.ndarray) -> list[tuple[Any, ...]]:
    """Every step's (obs, reward, terminated, truncated, pose) with next-step autoreset done by
    hand: after an episode ends, the next step resets instead (reward 0, flags False)."""
    obs, info = env.reset(seed=seed)
    out: list[tuple[Any, ...]] = [(obs, 0.0, False, False, info["pose"])]
    done = False
    for a in actions:
        if done:
            obs, info = env.reset()
            reward, terminated, truncated = 0.0, False, False
        else:
            obs, r, terminated, truncated, info = env.step(a)
            reward = float(r)
        done = terminated or truncated
        out.append((obs, reward, terminated, truncated, info["pose"]))
    return out


@settings(max_examples=10, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    maze=st.sampled_from(["paper", "gen:3:1", "zigzag"]),
    reality_gap=st.booleans(),
    gap_model=st.sampled_from(["trial", "step"]),
)
def test_vector_env_agrees_with_single_envs_step_for_step(
    seed: int, maze: str, reality_gap: bool, gap_model: str
) -> None:
    n, length = 3, 80
    kwargs: dict[str, Any] = {
        "maze": maze,
        "steps": 12,
        "reality_gap": reality_gap,
        "world": {"gap_model": gap_model, "stuck_after": 2},
    }
    actions = random_actions(seed, length, (n, 2))
    singles = [run_single(EvBotMazeEnv(**kwargs), seed + i, actions[:, i]) for i in range(n)]
    envs = EvBotMazeVectorEnv(n, **kwargs)
    obs, info = envs.reset(seed=seed)
    for i in range(n):
        assert (obs[i] == singles[i][0][0]).all()
        assert (info["pose"][i] == singles[i][0][4]).all()
    for k in range(length):
        obs, rewards, terminated, truncated, info = envs.step(actions[k])
        assert envs.observation_space.contains(obs)
        for i in range(n):
            s_obs, s_reward, s_term, s_trunc, s_pose = singles[i][k + 1]
            assert (obs[i] == s_obs).all()
            assert rewards[i] == s_reward
            assert (terminated[i], truncated[i]) == (s_term, s_trunc)
            assert (info["pose"][i] == s_pose).all()


@pytest.mark.parametrize("reality_gap", [False, True])
def test_vector_env_is_gymnasiums_sync_vector_env_of_single_envs(reality_gap: bool) -> None:
    """Against gymnasium's own SyncVectorEnv (next-step autoreset) of single envs, the reference
    of the vector API: the same observations, rewards, flags and poses at every step."""
    n = 4
    kwargs: dict[str, Any] = {
        "maze": "gen:3:5",
        "steps": 9,
        "reality_gap": reality_gap,
        "world": {"gap_model": "step"},
    }
    ours = EvBotMazeVectorEnv(n, **kwargs)
    theirs = SyncVectorEnv(
        [lambda: EvBotMazeEnv(**kwargs) for _ in range(n)], autoreset_mode=AutoresetMode.NEXT_STEP
    )
    obs, info = ours.reset(seed=11)
    ref_obs, ref_info = theirs.reset(seed=11)
    assert (obs == ref_obs).all() and (info["pose"] == ref_info["pose"]).all()
    for actions in random_actions(11, 60, (n, 2)):
        *got, info = ours.step(actions)
        *expected, ref_info = theirs.step(actions)
        for x, y in zip(got, expected, strict=True):
            assert np.array_equal(x, y)
        assert (info["pose"] == ref_info["pose"]).all()


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    reality_gap=st.booleans(),
    gap_model=st.sampled_from(["trial", "step"]),
)
def test_same_seed_same_episode_and_observations_in_the_space(
    seed: int, reality_gap: bool, gap_model: str
) -> None:
    actions = random_actions(seed, 40, (2,))
    kwargs: dict[str, Any] = {
        "maze": "gen:4:2",
        "steps": 40,
        "reality_gap": reality_gap,
        "world": {"gap_model": gap_model},
    }
    first = run_single(EvBotMazeEnv(**kwargs), seed, actions)
    again = run_single(EvBotMazeEnv(**kwargs), seed, actions)
    space = EvBotMazeEnv(**kwargs).observation_space
    for a, b in zip(first, again, strict=True):
        assert space.contains(a[0])
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_vector_env_autoresets_on_the_next_step() -> None:
    envs = EvBotMazeVectorEnv(2, maze="corridor", steps=3)
    envs.reset(seed=5)
    standing = np.zeros((2, 2))
    for _ in range(2):
        _, _, terminated, truncated, _ = envs.step(standing)
        assert not truncated.any() and not terminated.any()
    _, _, _, truncated, info = envs.step(standing)
    assert truncated.all()
    before = info["pose"]
    obs, rewards, terminated, truncated, info = envs.step(np.ones((2, 2)))  # ignored: a reset
    assert not (terminated.any() or truncated.any()) and (rewards == 0).all()
    assert (info["components"] == 0).all()
    assert not (info["pose"] == before).all(axis=1).any()  # new start poses
    assert envs.observation_space.contains(obs)


def test_gymnasium_episode_statistics_report_eq12_returns() -> None:
    """gymnasium's RecordEpisodeStatistics on the vector env: every finished episode's return is
    Eq 12 of its final terms."""
    envs = RecordEpisodeStatistics(
        gymnasium.make_vec(ENV_ID, num_envs=4, vectorization_mode="vector_entry_point", steps=20)
    )
    envs.reset(seed=3)
    envs.action_space.seed(3)
    finished = 0
    for _ in range(60):
        _, _, _, _, info = envs.step(envs.action_space.sample())
        if "episode" in info:
            ended = info["_episode"]
            score = fitness(info["components"][ended], FitnessWeights())
            np.testing.assert_allclose(info["episode"]["r"][ended], score, rtol=0, atol=1e-9)
            finished += int(ended.sum())
    assert finished >= 8


def test_rgb_array_shows_the_maze_and_the_robot() -> None:
    env = EvBotMazeEnv(maze="arena", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame is not None and frame.dtype == np.uint8 and frame.ndim == 3
    red = (frame == (200, 30, 30)).all(axis=2)
    assert 0 < red.sum() < frame.shape[0] * frame.shape[1] // 20


def python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(encoding="utf-8"), re.S)


@pytest.mark.parametrize("index", range(len(python_blocks(ROOT / "docs" / "gym.md"))))
def test_the_docs_examples_run(index: int, capsys: pytest.CaptureFixture[str]) -> None:
    exec(python_blocks(ROOT / "docs" / "gym.md")[index], {"__name__": "docs_gym"})
    assert capsys.readouterr().out.strip()


@pytest.mark.slow
def test_the_bench_runs_on_a_tiny_size() -> None:
    done = subprocess.run(
        [sys.executable, "bench/gym.py", "--batch", "8", "--seconds", "0.05", "--rounds", "1"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "vector / single" in done.stdout
