"""Eq 12 fitness, start poses, reality-gap draws, determinism and slicing independence."""

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.errors import MazeError
from evorobotics.evaluate import (
    DESCRIPTORS,
    GAP_CACHE_STEPS,
    PATH_STEPS,
    PATH_TRIALS,
    START_CACHE,
    _cached_start_poses,
    check_config,
    draw_gap,
    evaluate,
    implausible,
    record_path,
    start_poses,
    trial_steps,
    unseen_paths,
    validation_set,
)
from evorobotics.evolution import validate
from evorobotics.explore import explore
from evorobotics.fitness import COMPONENTS, fitness, mean_fitness
from evorobotics.maze import Maze, load_maze, parse_maze
from evorobotics.seeds import Purpose, rng
from evorobotics.sim import DEFAULT_WORLD, body_hits_wall, whisker_bits
from schemas.network import PRESETS
from schemas.run import FitnessWeights, RunConfig, ValidationConfig
from schemas.world import GapRobot, World


def test_eq12_with_paper_weights() -> None:
    assert COMPONENTS == ("curve_length", "net_offset", "max_offset", "stuck")
    comps = np.array([[1.0, 0.5, 0.75, 1.0], [2.0, 0.5, 0.75, 0.0]])
    assert fitness(comps, FitnessWeights()).tolist() == [-25.0, 25.0]
    assert fitness(comps, FitnessWeights(k1=1.0, k4=0.0)).tolist() == [26.0, 27.0]
    assert mean_fitness(comps[None], FitnessWeights()).tolist() == [0.0]
    with pytest.raises(ValueError):
        fitness(np.zeros((2, 3)), FitnessWeights())


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**40), generation=st.integers(0, 1000))
def test_start_poses_are_free_and_deterministic(seed: int, generation: int) -> None:
    maze = load_maze("paper")
    poses = start_poses(maze, seed, generation, 5)
    assert poses.shape == (5, 3)
    assert not body_hits_wall(maze, poses).any()
    assert not whisker_bits(maze, poses).any()
    assert np.array_equal(poses, start_poses(maze, seed, generation, 5))
    assert not np.array_equal(poses, start_poses(maze, seed, generation + 1, 5))
    assert np.array_equal(poses[:2], start_poses(maze, seed, generation, 2))


def numpy_start_poses(
    maze: Maze, seed: int, generation: int, trials: int, params: World
) -> np.ndarray:
    """The start-pose draw as first written: rounds of 64, the numpy geometry, no cache."""
    gen = rng(seed, generation, Purpose.START_POSES)
    accepted = [np.empty((0, 3))]
    while sum(len(a) for a in accepted) < trials:
        cand = np.column_stack(
            [
                gen.uniform(0.0, maze.width, 64),
                gen.uniform(0.0, maze.height, 64),
                gen.uniform(-np.pi, np.pi, 64),
            ]
        )
        free = ~body_hits_wall(maze, cand, params) & ~whisker_bits(maze, cand, params).any(axis=1)
        accepted.append(cand[free])
    return np.concatenate(accepted)[:trials]


@settings(max_examples=25, deadline=None)
@given(
    name=st.sampled_from(["paper", "arena", "corridor", "zigzag", "gen:4:2"]),
    params=st.sampled_from([DEFAULT_WORLD, World(whisker_range=0.1), World(body_length=0.3)]),
    seed=st.integers(0, 2**40),
    generation=st.integers(0, 1000),
    trials=st.integers(1, 80),
)
def test_start_poses_are_the_numpy_draws_bit_for_bit(
    name: str, params: World, seed: int, generation: int, trials: int
) -> None:
    maze = load_maze(name)
    expected = numpy_start_poses(maze, seed, generation, trials, params).tobytes()
    assert start_poses(maze, seed, generation, trials, params).tobytes() == expected
    assert start_poses(maze, seed, generation, trials, params).tobytes() == expected  # cached


def test_start_poses_cache_cannot_be_corrupted_and_is_bounded() -> None:
    maze = load_maze("paper")
    poses = start_poses(maze, 21, 3, 4)
    expected = poses.copy()
    with pytest.raises(ValueError, match="read-only"):
        poses[0, 0] = 0.0
    with pytest.raises(ValueError):
        poses.flags.writeable = True
    assert np.array_equal(start_poses(maze, 21, 3, 4), expected)
    gap = draw_gap(21, 3, 4)
    with pytest.raises(ValueError, match="read-only"):
        gap.motor_gain[0, 0] = 2.0
    assert np.array_equal(draw_gap(21, 3, 4).motor_gain, gap.motor_gain)
    for g in range(START_CACHE + 5):
        start_poses(maze, 22, g, 2)
    assert _cached_start_poses.cache_info().currsize <= START_CACHE
    assert np.array_equal(start_poses(maze, 21, 3, 4), expected)  # evicted and drawn again
    with pytest.raises(ValueError, match="trials"):
        start_poses(maze, 0, 0, -1)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    k=st.integers(1, 40),
    trials=st.integers(1, 30),
    k4=st.floats(0.0, 100.0),
)
def test_mean_fitness_is_numpy_mean_bit_for_bit(seed: int, k: int, trials: int, k4: float) -> None:
    g = np.random.default_rng(seed)
    comps = np.concatenate(
        [g.exponential(1.0, (k, trials, 3)), g.integers(0, 2, (k, trials, 1))], axis=-1
    )
    weights = FitnessWeights(k1=0.5, k4=k4)
    expected = fitness(comps, weights).mean(axis=1)
    got = mean_fitness(comps, weights)
    assert got.dtype == np.float64 and got.tobytes() == expected.tobytes()


def test_no_room_for_a_start_pose() -> None:
    with pytest.raises(MazeError, match="no room"):
        start_poses(parse_maze("#####\n#...#\n#####\n"), 0, 0, 1)


def test_reality_gap_draws_in_range() -> None:
    gap = draw_gap(5, 3, 200)
    assert gap.whisker_range.min() >= 0.025 and gap.whisker_range.max() <= 0.1
    assert gap.motor_gain.min() >= 0.85 and gap.motor_gain.max() <= 1.15
    assert gap.whisker_range.max() - gap.whisker_range.min() > 0.06  # spans the range
    again = draw_gap(5, 3, 2)  # trial t's draw depends on t only
    assert np.array_equal(again.whisker_range, gap.whisker_range[:2])
    assert not np.array_equal(draw_gap(5, 4, 2).motor_gain, again.motor_gain)


def genomes(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, 1.5, (n, 222))


@settings(max_examples=15, deadline=None)
@given(
    gap=st.sampled_from([None, "trial", "step"]),
    cuts=st.lists(st.integers(1, 29), max_size=4, unique=True).map(sorted),
    threads=st.integers(1, 3),
)
def test_evaluate_is_deterministic_and_slice_independent(
    gap: str | None, cuts: list[int], threads: int
) -> None:
    """A job's slice of a generation, on any threads, sees the trials' poses and gap draws of
    the whole: the same bits however a generation is cut among workers (spans and restarts
    replay whole slices: tests/test_distributed.py runs them against `evolve`)."""
    world = World(gap_model="trial" if gap is None else gap)
    gap_on = "off" if gap is None else "on"
    config = RunConfig(seed=11, steps=60, reality_gap=gap_on, nominal_first=0.0, world=world)
    pop = genomes(30)
    whole = evaluate(config, 4, pop)
    assert whole.fitness.shape == (30,)
    assert whole.components.shape == (30, 3, 4)
    assert np.array_equal(whole.fitness, mean_fitness(whole.components, config.fitness))
    bounds = [0, *cuts, 30]
    parts = [evaluate(config, 4, pop[a:b], threads=threads) for a, b in itertools.pairwise(bounds)]
    assert np.concatenate([p.fitness for p in parts]).tobytes() == whole.fitness.tobytes()
    assert np.concatenate([p.components for p in parts]).tobytes() == whole.components.tobytes()
    assert np.concatenate([p.descriptors for p in parts]).tobytes() == whole.descriptors.tobytes()
    assert not np.array_equal(evaluate(config, 5, pop).fitness, whole.fitness)


def test_descriptors_are_the_trials_normalised_and_averaged() -> None:
    config = RunConfig(seed=3, steps=60, reality_gap="off")
    pop = genomes(5, seed=8)
    ev = evaluate(config, 1, pop)
    assert DESCRIPTORS == ("final_x", "final_y", "max_offset", "coverage")
    assert ev.descriptors.shape == (5, 4) and ev.descriptors.dtype == np.float64
    assert ((ev.descriptors >= 0) & (ev.descriptors <= 1)).all()
    maze = load_maze("paper")
    finals, cells = [], []
    for pose in start_poses(maze, 3, 1, config.trials):  # individual 4's trials, recorded
        rec = record_path(config, pop[4], pose, 60)
        assert rec.poses is not None and rec.cells is not None
        finals.append(rec.poses_final[0])
        cell = maze.cell_size
        visited = {(math.floor(x / cell), math.floor(y / cell)) for x, y, _ in rec.poses[0]}
        assert rec.cells[0] == len(visited)
        cells.append(len(visited))
    assert ev.descriptors[4, 0] == pytest.approx(np.mean([f[0] for f in finals]) / maze.width)
    assert ev.descriptors[4, 1] == pytest.approx(np.mean([f[1] for f in finals]) / maze.height)
    diagonal = np.hypot(maze.width, maze.height)
    assert ev.descriptors[4, 2] == pytest.approx(ev.components[4, :, 2].mean() / diagonal)
    assert ev.descriptors[4, 3] == pytest.approx(np.mean(cells) / (~maze.solid).sum())


def test_reality_gap_changes_fitness_and_stuck_is_penalised() -> None:
    pop = genomes(40, seed=3)
    plain = evaluate(RunConfig(seed=2, reality_gap="off"), 0, pop)
    gapped = evaluate(RunConfig(seed=2, nominal_first=0.0), 0, pop)  # the gap is on by default
    assert not np.array_equal(plain.fitness, gapped.fitness)
    stuck = plain.components[..., 3]
    assert set(np.unique(stuck)) <= {0.0, 1.0} and stuck.any()
    per_trial = 20 * plain.components[..., 1] + 20 * plain.components[..., 2] - 50 * stuck
    assert np.allclose(plain.fitness, per_trial.mean(axis=1))


def test_record_path_matches_evaluation() -> None:
    config = RunConfig(seed=9, reality_gap="off")
    pop = genomes(3, seed=5)
    ev = evaluate(config, 2, pop)
    pose = start_poses(load_maze("paper"), 9, 2, 3)[1]
    rec = record_path(config, pop[2], pose, trial_steps(config))
    assert rec.poses is not None and rec.whiskers is not None and rec.motors is not None
    assert rec.poses.shape == (1, 241, 3) and rec.whiskers.shape == (1, 240, 5)
    assert rec.whiskers.dtype == np.uint8 and rec.motors.shape == (1, 240, 2)
    assert np.array_equal(rec.poses[0, 0], pose)
    assert np.abs(rec.motors).max() <= 1.0
    assert rec.components[0].tobytes() == ev.components[2, 1].tobytes()


def test_unseen_paths_are_recorded_trials_from_the_next_generations_poses() -> None:
    # Fig 6's trials in one batch are each the batch-1 recording from its start pose
    config = RunConfig(generations=7, seed=4, world=World(whisker_range=0.08))
    genome = genomes(1, 3)[0]
    paths = unseen_paths(config, genome)
    assert paths.poses is not None and paths.poses.shape == (PATH_TRIALS, PATH_STEPS + 1, 3)
    for k, start in enumerate(start_poses(load_maze("paper"), 4, 7, PATH_TRIALS)):
        one = record_path(config, genome, start, PATH_STEPS)
        assert one.poses is not None and one.poses[0].tobytes() == paths.poses[k].tobytes()
        assert one.max_offset[0] == paths.max_offset[k] and one.stuck[0] == paths.stuck[k]


def test_bad_genome_shape() -> None:
    with pytest.raises(ValueError, match="genomes"):
        evaluate(RunConfig(), 0, np.zeros((2, 10)))


STEP = World(gap_model="step")


def test_the_trial_gap_model_draws_as_documented() -> None:
    # five distances per trial (left to right), then two gains around the world's nominal
    # ones, from the trial's own stream: never reordered
    world = World(motor_gain=(0.9, 1.1))
    gap = draw_gap(8, 2, 3, world, steps=50)
    assert gap.whisker_range.shape == (3, 5)
    for t in range(3):
        gen = rng(8, 2, Purpose.REALITY_GAP, t)
        assert gap.whisker_range[t].tobytes() == gen.uniform(0.025, 0.1, 5).tobytes()
        gains = np.array([0.9, 1.1]) * gen.uniform(0.85, 1.15, 2)
        assert gap.motor_gain[t].tobytes() == gains.tobytes()
    assert draw_gap(8, 2, 3, world).whisker_range.tobytes() == gap.whisker_range.tobytes()


GAP_ROBOT = st.builds(
    GapRobot,
    whisker_range=st.tuples(*[st.floats(0.0, 0.3)] * 5),
    whisker_uncertainty=st.tuples(*[st.floats(0.0, 0.05)] * 5),
    motor_gain=st.tuples(st.floats(0.5, 1.5), st.floats(0.5, 1.5)),
    motor_gain_uncertainty=st.tuples(st.floats(0.0, 0.1), st.floats(0.0, 0.1)),
)


@settings(max_examples=30, deadline=None)
@given(
    robots=st.lists(GAP_ROBOT, min_size=1, max_size=4),
    seed=st.integers(0, 2**40),
    model=st.sampled_from(["trial", "step"]),
)
def test_the_colony_gap_draws_each_trial_within_one_calibrated_robot(
    robots: list[GapRobot], seed: int, model: str
) -> None:
    """`reality_gap: "colony"`: a trial's robot is one of the calibrated robots, every
    whisker range and gain inside that robot's value +- uncertainty (every step's too)."""
    world = World(gap_robots=tuple(robots), gap_model=model)
    gap = draw_gap(seed, 3, 12, world, steps=7)

    def inside(robot: GapRobot, ranges: np.ndarray, gains: np.ndarray) -> bool:
        (wlo, whi), (glo, ghi) = robot.whisker_bounds(), robot.gain_bounds()
        return bool(
            ((np.array(wlo) <= ranges) & (ranges <= np.array(whi))).all()
            and ((np.array(glo) <= gains) & (gains <= np.array(ghi))).all()
        )

    for t in range(12):
        ranges = gap.whisker_range[t].reshape(-1, 5)
        assert any(inside(r, ranges, gap.motor_gain[t]) for r in robots)
    again = draw_gap(seed, 3, 12, world, steps=7)
    assert again.whisker_range.tobytes() == gap.whisker_range.tobytes()


def test_a_colony_gap_needs_its_robots_and_only_it_takes_them() -> None:
    robot = GapRobot(
        whisker_range=(0.05,) * 5,
        whisker_uncertainty=(0.001,) * 5,
        motor_gain=(1.0, 0.9),
        motor_gain_uncertainty=(0.01, 0.01),
    )
    with pytest.raises(ValueError, match="only under reality_gap 'colony'"):
        RunConfig(world=World(gap_robots=(robot,)))
    with pytest.raises(ValueError, match="needs the calibrated robots"):
        check_config(RunConfig(reality_gap="colony"))
    colony = RunConfig(reality_gap="colony", world=World(gap_robots=(robot,)), trials=4)
    check_config(colony)
    assert colony.gap and colony.training_world == colony.world  # train_whisker_range unused


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**40),
    generation=st.integers(0, 1000),
    trials=st.integers(1, 6),
    steps=st.integers(2, 60),
)
def test_step_gap_model_draws_per_step_and_whisker(
    seed: int, generation: int, trials: int, steps: int
) -> None:
    gap = draw_gap(seed, generation, trials, STEP, steps=steps)
    r = gap.whisker_range
    assert r.shape == (trials, steps, 5) and gap.motor_gain.shape == (trials, 2)
    assert ((r >= 0.025) & (r <= 0.1)).all()
    assert (r[:, 1:] != r[:, :-1]).all() and (r[..., 1:] != r[..., :-1]).all()
    assert not r.flags.writeable and not gap.motor_gain.flags.writeable
    # the gains are the trial model's; a longer trial extends a shorter one's draws
    trial = draw_gap(seed, generation, trials)
    assert gap.motor_gain.tobytes() == trial.motor_gain.tobytes()
    longer = draw_gap(seed, generation, trials, STEP, steps=steps + 7)
    assert longer.whisker_range[:, :steps].tobytes() == r.tobytes()
    assert draw_gap(seed, generation, trials, STEP, steps=steps).whisker_range.tobytes() == (
        r.tobytes()
    )


def test_step_gap_draws_beyond_the_cache_are_the_same_draws() -> None:
    big = GAP_CACHE_STEPS // 2 + 1
    uncached = draw_gap(3, 1, 2, STEP, Purpose.VALIDATION_GAP, big)
    cached = draw_gap(3, 1, 2, STEP, Purpose.VALIDATION_GAP, 10)
    assert (
        uncached.whisker_range.shape == (2, big, 5) and not uncached.whisker_range.flags.writeable
    )
    assert uncached.whisker_range[:, :10].tobytes() == cached.whisker_range.tobytes()
    with pytest.raises(ValueError, match="steps"):
        draw_gap(3, 1, 2, STEP)


def test_the_step_gap_model_changes_fitness() -> None:
    pop = genomes(20, seed=4)
    trial = evaluate(RunConfig(seed=2, nominal_first=0.0), 0, pop)
    step = evaluate(RunConfig(seed=2, nominal_first=0.0, world=STEP), 0, pop)
    assert not np.array_equal(trial.fitness, step.fitness)


def test_validation_and_exploration_take_the_step_gap_model() -> None:
    v = ValidationConfig(poses=6, steps=60, candidates=3)
    config = RunConfig(seed=4, reality_gap=True, world=STEP, validation=v)
    poses, gap = validation_set(config)
    assert poses.shape == (6, 3) and gap is not None and gap.whisker_range.shape == (6, 60, 5)
    pop = genomes(3, seed=6)
    together = validate(config, pop)
    for i in range(3):
        alone = validate(config, pop[i : i + 1])
        assert alone.score[0] == together.score[i] and alone.roaming[0] == together.roaming[i]
    trial = validate(config.model_copy(update={"world": World()}), pop)
    assert not np.array_equal(trial.score, together.score)
    spec = PRESETS["paper-best"]
    e = explore(spec, pop[0], poses=5, steps=60, seed=2, reality_gap=True, world=STEP)
    again = explore(spec, pop[0], poses=5, steps=60, seed=2, reality_gap=True, world=STEP)
    assert e == again
    assert e != explore(spec, pop[0], poses=5, steps=60, seed=2, reality_gap=True)


@settings(max_examples=20, deadline=None)
@given(
    generations=st.integers(1, 40),
    nominal_first=st.floats(0.0, 0.99),
    generation=st.integers(0, 39),
)
def test_the_curriculum_trains_nominal_first_then_under_the_gap(
    generations: int, nominal_first: float, generation: int
) -> None:
    """Generations before round(nominal_first x generations) are the nominal run's, bit for
    bit; the later ones draw the gap."""
    config = RunConfig(seed=6, steps=40, generations=generations, nominal_first=nominal_first)
    nominal = config.model_copy(update={"reality_gap": "off"})
    pop = genomes(6, seed=2)
    same = evaluate(config, generation, pop).fitness.tobytes() == (
        evaluate(nominal, generation, pop).fitness.tobytes()
    )
    switch = round(nominal_first * generations)
    assert config.trains_under_gap(generation) == (generation >= switch)
    assert same == (generation < switch)


def test_a_fast_calibrated_robot_is_no_forgery_under_the_colony_gap() -> None:
    """A colony-gap run's trials draw wheel gains from the calibrated robots, which may be
    faster than the paper's gap allows: an honest robot driving straight at full speed with
    wheels of 1.6 (beyond 1.15) is within the bound, going farther than that robot can is not."""
    fast = GapRobot(
        whisker_range=(0.05,) * 5,
        whisker_uncertainty=(0.0,) * 5,
        motor_gain=(1.6, 1.6),
        motor_gain_uncertainty=(0.0, 0.0),
    )
    config = RunConfig(
        population=4, trials=1, steps=40, reality_gap="colony", world=World(gap_robots=(fast,))
    )
    reach = trial_steps(config) * config.world.step_length * 1.6
    honest = np.array([[[reach, reach, reach, 0.0]]])
    descriptors = np.full((1, 4), 0.5)
    fitness = mean_fitness(honest, config.fitness)
    assert implausible(config, fitness, honest, descriptors) is None
    beyond = honest * np.array([1.01, 0.0, 0.0, 0.0])
    forged = mean_fitness(beyond, config.fitness)
    assert "reach at full speed" in str(implausible(config, forged, beyond, descriptors))


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**40),
    steps=st.integers(1, 400),
    gap=st.sampled_from(["on", "off"]),
    gain=st.floats(0.5, 3.0),
    preset=st.sampled_from(["paper-best", "reactive"]),
)
def test_honest_evaluations_are_never_implausible_and_forged_reach_is(
    seed: int, steps: int, gap: str, gain: float, preset: str
) -> None:
    """The physics bound on workers' claims never refuses a real evaluation (any seed, trial
    length, gap, wheel gain, network); a curve length beyond full speed, a fitness not Eq 12
    of its components and a descriptor outside [0, 1] or not a number are refused."""
    world = World(motor_gain=(gain, 1.0))
    config = RunConfig(
        population=6, trials=2, steps=steps, seed=seed, reality_gap=gap, world=world,
        network=preset,
    )  # fmt: skip
    genomes = rng(seed, 0, Purpose.BODY_GAP).uniform(-3, 3, (6, config.network_spec.weight_count))
    ev = evaluate(config, 0, genomes)
    f, c, d = ev.fitness, ev.components, ev.descriptors
    assert implausible(config, f, c, d) is None
    far = c.copy()
    fastest = max(world.motor_gain) * (1 + world.gap_motor_gain)
    far[0, 0, 0] = steps * world.dt * world.max_speed * fastest * 1.01
    assert "reach at full speed" in str(implausible(config, f, far, d))
    assert "not Eq 12" in str(implausible(config, f + 1e-3, c, d))
    for bad in (1.0 + 1e-12, -1e-12, np.nan, np.inf):
        forged = d.copy()
        forged[-1, 2] = bad
        assert implausible(config, f, c, forged) == "a descriptor outside [0, 1]"
