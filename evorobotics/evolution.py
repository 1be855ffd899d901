"""Local evolution: the run loop every role composes identically, and the job slices.

An individual's fitness depends on the config, the generation and its own genome only (trial
conditions are drawn per generation, robots are independent), never on which other genomes
share its `evaluate` call. So how a generation is cut into contiguous jobs (`job_slices`; the
server cuts by the run's `job_size` or, with zenoh workers, one job per live worker) cannot
change a run, and `evolve` evaluates the whole generation in one call: bit-identical fitness
arrays either way.
`best_document` names the best of a generation on training (rank 0); `champion` names a
finished run's controller the same way for `colony evolve` and the server: the best of its
final population on the run's validation set (`RunConfig.validation`, docs/evolve.md).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from evorobotics.document import ControllerDocument
from evorobotics.evaluate import (
    DESCRIPTORS,
    available_cores,
    draw_gap,
    evaluate,
    map_slices,
    robot_steps,
    start_poses,
    thread_slices,
    validation_set,
)
from evorobotics.explore import watch
from evorobotics.fitness import mean_fitness
from evorobotics.ga import GAParams, GAState, TellMetrics, ask, ga_rng, init, rank, tell
from evorobotics.layout import layout
from evorobotics.maze import load_maze
from evorobotics.seeds import Purpose
from evorobotics.sim import Gap
from evorobotics.stats import wilson
from evorobotics.strategies import Archive, make_strategy
from schemas.run import (
    HeldOutScore,
    Proportion,
    RunConfig,
    ValidationConfig,
    ValidationScore,
    WorldScore,
)
from schemas.wire import Stage
from schemas.world import World


def job_slices(population: int, job_size: int) -> list[tuple[int, int]]:
    """Contiguous [start, stop) slices of `job_size` covering 0..population, in order."""
    if population < 1:
        raise ValueError(f"population must be >= 1, got {population}")
    if job_size < 1:
        raise ValueError(f"job_size must be >= 1, got {job_size}")
    return [(a, min(a + job_size, population)) for a in range(0, population, job_size)]


@dataclass(frozen=True)
class GenerationSummary:
    """One completed generation's fitness statistics (over finite values; NaN if none)."""

    generation: int
    best: float
    mean: float
    worst: float
    nan_count: int


@dataclass(frozen=True)
class EvolutionResult:
    """Everything a finished local run produced; arrays are those of the last generation."""

    state: GAState
    history: tuple[GenerationSummary, ...]
    best: ControllerDocument
    genomes: np.ndarray
    """(population, n_weights) the last generation evaluated, in ask() order."""
    fitness: np.ndarray
    """(population,) Eq 12 fitness of `genomes`."""
    components: np.ndarray
    """(population, trials, 4) per-trial (curve_length, net_offset, max_offset, stuck)."""
    archive: Archive | None = None
    """The final archive of a map-elites, cma-me or novelty run (`RunLoop.archive`)."""


def best_document(
    config: RunConfig,
    genomes: np.ndarray,
    fitness: np.ndarray,
    order: np.ndarray,
    *,
    generation: int,
    run: str | int = "local",
    rank: int = 0,
    validation: ValidationScore | None = None,
    test: HeldOutScore | None = None,
) -> ControllerDocument:
    """The controller document of training rank `rank` (`order[rank]`) of a completed generation.

    `order` is the ranking from `tell` (TellMetrics.order); a caller holding genomes already
    sorted fittest first passes `np.arange(n)`. The provenance says where it came from.
    """
    genomes = np.asarray(genomes)
    fitness = np.asarray(fitness)
    if genomes.ndim != 2 or fitness.shape != (genomes.shape[0],):
        raise ValueError(
            f"genomes must be (n, w) with fitness (n,), got {genomes.shape} and {fitness.shape}"
        )
    if not 0 <= rank < len(order):
        raise ValueError(f"rank {rank} is outside the {len(order)} ranked individuals")
    if generation < 0:
        raise ValueError(f"generation must be >= 0, got {generation}")
    top = int(order[rank])
    value = float(fitness[top])
    return ControllerDocument(
        spec=config.network_spec,
        weights=np.array(genomes[top], dtype=np.float64),
        fitness=value if np.isfinite(value) else None,
        provenance={"seed": config.seed, "generation": generation, "rank": rank, "run": run},
        validation=validation,
        world=config.world,
        test=test,
    )


@dataclass(frozen=True)
class Validated:
    """k candidates on the validation set: mean Eq 12, stuck and roaming fractions, each (k,)."""

    score: np.ndarray
    stuck: np.ndarray
    roaming: np.ndarray

    def scores(self) -> np.ndarray:
        """As a validate job's `Result.scores`: (k, 3) columns score, stuck, roaming."""
        return np.stack([self.score, self.stuck, self.roaming], axis=1)

    @staticmethod
    def from_scores(scores: np.ndarray) -> Validated:
        return Validated(*(np.ascontiguousarray(scores[:, i]) for i in range(3)))


VALIDATION_CHUNK_BYTES = 64 * 2**20
"""Under the per-step gap model validation trials are simulated in slices of candidates whose
copies of the gap's whisker draws take about this many bytes in all (over the threads)."""


def validate(config: RunConfig, genomes: np.ndarray, *, threads: int = 1) -> Validated:
    """Score k genomes (k, n_weights) on the run's validation set (`evaluate.validation_set`),
    in contiguous slices of candidates on `threads` threads (the same bits whatever the count).

    Each candidate runs every validation pose for `validation.steps` steps; a trial roams if
    it neither sticks nor is confined (`explore.confined`), the measure of the paper's claim.
    """
    v = config.validation
    if v.poses < 1:
        raise ValueError("validation is off (validation.poses = 0)")
    g = np.asarray(genomes, dtype=np.float64)
    poses, gap = validation_set(config)
    maze = load_maze(config.maze)
    most = (
        None
        if gap is None
        else max(1, VALIDATION_CHUNK_BYTES // (gap.whisker_range.nbytes * threads))
    )

    def scored(a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = b - a
        result = watch(
            config.network_spec,
            np.repeat(g[a:b], v.poses, axis=0),
            maze,
            np.tile(poses, (k, 1)),
            v.steps,
            config.world,
            None if gap is None else gap.tile(k),
        )
        trials = (k, v.poses)
        free = ~result.confined & ~result.stuck
        return (
            mean_fitness(result.components.reshape(*trials, 4), config.fitness),
            result.stuck.reshape(trials).mean(axis=1),
            free.reshape(trials).mean(axis=1),
        )

    parts = map_slices(scored, thread_slices(len(g), threads, most), threads)
    score, stuck, roaming = (np.concatenate([p[i] for p in parts]) for i in range(3))
    return Validated(score, stuck, roaming)


def ranking_validation(config: RunConfig) -> ValidationConfig:
    """The validation `rank_in_world` runs: the run's, or the default one without it."""
    return config.validation if config.validation.poses else ValidationConfig(test_poses=0)


def ranking_config(config: RunConfig, world: World) -> RunConfig:
    """The config `rank_in_world` validates a run's candidates with: `world` (a robot's
    calibrated world) without a reality gap, on `ranking_validation`'s set. Its world draws from
    no gap robots, so it is a valid config that crosses the wire as it is."""
    return config.model_copy(
        update={
            "world": world.model_copy(update={"gap_robots": ()}),
            "reality_gap": "off",
            "validation": ranking_validation(config),
        }
    )


Ranked = tuple[np.ndarray, Validated]
"""A ranking of candidates: their order, best first, and their scores (`rank_in_world`)."""


def ranked(scored: Validated) -> Ranked:
    """Candidates in the order `rank_in_world` gives them from their validation scores, with
    those scores: most roaming trials first, ties to the higher mean Eq 12, then to candidate
    order (lexsort's last key leads)."""
    return np.lexsort((np.arange(len(scored.score)), -scored.score, -scored.roaming)), scored


def rank_in_world(
    config: RunConfig, genomes: np.ndarray, world: World, *, threads: int = 1
) -> Ranked:
    """A run's candidates (k, n_weights) ranked for one robot, best first, with their scores:
    run from the run's validation poses in `world` (a robot's calibrated world, no reality gap
    drawn on top, `ranking_config`), `ranked`: the `rank` and `fit` replacement policies'
    order (docs/robots.md). Each candidate's row is its own, so rows scored in any slices, by
    anyone, rank the same (`ranked` of `Validated.from_scores`)."""
    return ranked(validate(ranking_config(config, world), genomes, threads=threads))


@dataclass(frozen=True)
class HeldOutTrials:
    """Test poses start:stop of a controller's held-out test, row 0 in the nominal world and
    row 1 in the test gap's: roaming and stuck (bool) and the largest offset from start (m),
    each (2, stop - start). Slices of poses concatenate to the whole test, bit for bit."""

    roaming: np.ndarray
    stuck: np.ndarray
    offset: np.ndarray

    def scores(self) -> np.ndarray:
        """As a test job's `Result.scores`: (k, 6) columns roaming, stuck and offset, each in
        the nominal world then the gap's."""
        return np.concatenate([self.roaming.T, self.stuck.T, self.offset.T], axis=1, dtype=float)

    @staticmethod
    def from_scores(scores: np.ndarray) -> HeldOutTrials:
        return HeldOutTrials(
            scores[:, 0:2].T == 1.0, scores[:, 2:4].T == 1.0, np.ascontiguousarray(scores[:, 4:6].T)
        )

    @staticmethod
    def concatenate(parts: list[HeldOutTrials]) -> HeldOutTrials:
        return HeldOutTrials(
            *(np.concatenate([getattr(p, f) for p in parts], axis=1) for f in _HELD_OUT_FIELDS)
        )


_HELD_OUT_FIELDS = ("roaming", "stuck", "offset")


def held_out_trials(
    config: RunConfig, weights: np.ndarray, start: int, stop: int, *, threads: int = 1
) -> HeldOutTrials:
    """Test poses start:stop of `held_out` for one controller, in slices of poses on
    `threads` threads; a job of the held-out test is one such slice."""
    v = config.validation
    if not 0 <= start < stop <= v.test_poses:
        raise ValueError(f"test poses {start}:{stop} outside the test's {v.test_poses}")
    maze = load_maze(config.maze)
    poses = start_poses(maze, config.seed, 0, v.test_poses, config.world, Purpose.TEST)[start:stop]
    gap = draw_gap(config.seed, 0, v.test_poses, config.world, Purpose.TEST_GAP, v.steps)
    gap = Gap(gap.whisker_range[start:stop], gap.motor_gain[start:stop])
    w = np.asarray(weights, dtype=np.float64).reshape(1, -1)

    def run(world: Gap | None, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        result = watch(
            config.network_spec,
            np.repeat(w, b - a, axis=0),
            maze,
            poses[a:b],
            v.steps,
            config.world,
            None if world is None else Gap(world.whisker_range[a:b], world.motor_gain[a:b]),
        )
        free = ~result.confined & ~result.stuck
        return free, result.stuck, result.max_offset

    rows = []
    for world in (None, gap):
        parts = map_slices(partial(run, world), thread_slices(len(poses), threads), threads)
        rows.append([np.concatenate([p[i] for p in parts]) for i in range(3)])
    return HeldOutTrials(*(np.stack([row[i] for row in rows]) for i in range(3)))


def held_out_score(config: RunConfig, trials: HeldOutTrials) -> HeldOutScore:
    """The held-out test's figures from all its trials (`held_out_trials` of every pose)."""
    v = config.validation
    n = trials.roaming.shape[1]
    if n != v.test_poses:
        raise ValueError(f"{n} test trials for a test of {v.test_poses} poses")

    def proportion(hits: np.ndarray) -> Proportion:
        low, high = wilson(int(hits.sum()), n)
        return Proportion(value=float(hits.mean()), low=low, high=high)

    def world(i: int) -> WorldScore:
        return WorldScore(
            roaming=proportion(trials.roaming[i]),
            stuck=proportion(trials.stuck[i]),
            max_offset=float(trials.offset[i].mean()),
        )

    return HeldOutScore(
        poses=v.test_poses, steps=v.steps, seed=config.seed, nominal=world(0), gap=world(1)
    )


def held_out(config: RunConfig, weights: np.ndarray, *, threads: int = 1) -> HeldOutScore:
    """A controller's held-out test: `validation.test_poses` start poses from Purpose.TEST,
    each run for `validation.steps` steps in the nominal world and in a world of the reality
    gap drawn from Purpose.TEST_GAP (whatever the run trained in). Neither stream chose the
    champion, so these are the figures to quote about it."""
    v = config.validation
    if v.test_poses < 1:
        raise ValueError("the test is off (validation.test_poses = 0)")
    return held_out_score(
        config, held_out_trials(config, weights, 0, v.test_poses, threads=threads)
    )


def champion_scores(
    config: RunConfig, stage: Stage, genomes: np.ndarray, start: int, stop: int
) -> np.ndarray:
    """A champion stage job's `Result.scores`: candidates `genomes` (candidates start:stop)
    on the validation set, or test poses start:stop of the one genome."""
    if stage == "validate":
        return validate(config, genomes).scores()
    if stage == "test":
        return held_out_trials(config, genomes[0], start, stop).scores()
    raise ValueError(f"{stage} is no champion stage")


def stage_robot_steps(config: RunConfig, stage: Stage, n: int) -> int:
    """Robot-steps of a job of n individuals (`train`), candidates (`validate`, or `rank` of
    a `ranking_config`) or test poses."""
    v = config.validation
    if stage == "train":
        return robot_steps(config, n)
    return n * v.steps * (v.poses if stage in ("validate", "rank") else 2)


def validation_pick(scored: Validated) -> int:
    """The validated candidate the champion is: the first `ranked` (candidates are in
    training-rank order, so ties go to the better training rank)."""
    return int(ranked(scored)[0][0])


def champion_document(
    config: RunConfig,
    genomes: np.ndarray,
    fitness: np.ndarray,
    order: np.ndarray,
    scored: Validated | None,
    test: HeldOutScore | None,
    *,
    generation: int,
    run: str | int = "local",
) -> ControllerDocument:
    """The champion's document from its candidates' validation (`validate` of
    `order[:validation.candidates]`; None with validation off: training rank 0) and the
    held-out test of the pick (`validation_pick`), wherever they were simulated."""
    v = config.validation
    if scored is None:
        return best_document(
            config, genomes, fitness, order, generation=generation, run=run, test=test
        )
    pick = validation_pick(scored)
    return best_document(
        config,
        genomes,
        fitness,
        order,
        generation=generation,
        run=run,
        rank=pick,
        validation=ValidationScore(
            poses=v.poses,
            steps=v.steps,
            seed=config.seed,
            candidates=len(scored.score),
            training_rank=pick,
            score=float(scored.score[pick]),
            stuck=float(scored.stuck[pick]),
            roaming=float(scored.roaming[pick]),
        ),
        test=test,
    )


def champion(
    config: RunConfig,
    genomes: np.ndarray,
    fitness: np.ndarray,
    order: np.ndarray,
    *,
    generation: int,
    run: str | int = "local",
    threads: int = 1,
) -> ControllerDocument:
    """The controller a finished run exports: its final population's best on validation
    (simulated on `threads` threads).

    Training ranks a generation on a few short trials, so its rank 0 is partly luck (a
    winner's curse). The `config.validation.candidates` fittest on training are re-scored on
    the run's validation set (`validate`); the champion is `validation_pick` of them. Its
    document carries those figures, and its held-out test (`held_out`, with
    `validation.test_poses` > 0). With validation off it is training rank 0.
    """
    v = config.validation
    genomes = np.asarray(genomes)
    order = np.asarray(order)
    scored = validate(config, genomes[order[: v.candidates]], threads=threads) if v.poses else None
    pick = 0 if scored is None else validation_pick(scored)
    test = held_out(config, genomes[int(order[pick])], threads=threads) if v.test_poses else None
    return champion_document(
        config, genomes, fitness, order, scored, test, generation=generation, run=run
    )


def evaluate_population(
    config: RunConfig, generation: int, genomes: np.ndarray, *, threads: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fitness (n,), components (n, trials, 4) and descriptors (n, 4) (`evaluate.DESCRIPTORS`)
    of a generation's n = population genomes: `RunLoop.tell`'s arguments, in its order.

    One `evaluate` call for the whole population (on `threads` threads): bit-identical to
    evaluating it job by job in `job_slices` and concatenating (property-tested), without the
    per-call cost of each job.
    """
    genomes = np.asarray(genomes)
    if genomes.ndim != 2 or genomes.shape[0] != config.population:
        raise ValueError(
            f"genomes must be ({config.population}, n_weights), one row per individual, "
            f"got {genomes.shape}"
        )
    result = evaluate(config, generation, genomes, threads=threads)
    return result.fitness, result.components, result.descriptors


@dataclass(frozen=True)
class StrategyHistory:
    """What a run loop was told, generation by generation: with the config, the whole state of
    any strategy (`RunLoop.resume` replays it). Arrays only, for storage as raw bytes."""

    fitness: np.ndarray
    """(generations, population) fitness in ask() order."""
    descriptors: np.ndarray
    """(generations, population, 4) in `evaluate.DESCRIPTORS` order; NaN where none was told."""

    def __post_init__(self) -> None:
        f = np.asarray(self.fitness, dtype=np.float64)
        d = np.asarray(self.descriptors, dtype=np.float64)
        if f.ndim != 2 or d.shape != (*f.shape, len(DESCRIPTORS)):
            raise ValueError(
                f"history needs fitness (g, n) and descriptors (g, n, {len(DESCRIPTORS)}), "
                f"got {f.shape} and {d.shape}"
            )
        object.__setattr__(self, "fitness", f)
        object.__setattr__(self, "descriptors", d)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """{"fitness": ..., "descriptors": ...}, copies."""
        return {"fitness": self.fitness.copy(), "descriptors": self.descriptors.copy()}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> StrategyHistory:
        """The history `to_arrays` described; ValueError on other keys or shapes."""
        if set(arrays) != {"fitness", "descriptors"}:
            raise ValueError(
                f"history arrays must be fitness and descriptors, got {sorted(arrays)}"
            )
        return cls(arrays["fitness"], arrays["descriptors"])


@dataclass
class _Steps:
    """What a fork computed, keyed by the identity of the state it stepped from (`RunLoop.fork`):
    the genomes asked, and the state and metrics each told fitness (its bytes) gave."""

    asked: dict[int, tuple[GAState, np.ndarray]] = field(default_factory=dict)
    told: dict[tuple[int, bytes], tuple[GAState, GAState, TellMetrics]] = field(
        default_factory=dict
    )


class RunLoop:
    """The run loop every role drives: ask, evaluate (the caller's part), tell, for any strategy.

    `colony evolve`, the server's scheduler and a worker evolving a span all step a run through
    this object, so a strategy or an end-of-run step is added here once.

    State. `state` is a GAState after every strategy's `tell` (the generation counter and the
    told generation ranked by fitness, what a store shows). For `paper-ga` it is the whole
    state: `RunLoop(config, state)` goes on bit for bit from a stored one. The other strategies
    (config.strategy) hold Python objects (pycma, pyribs), so their state is the config plus
    `history` (fitness and descriptors told per generation, arrays only):
    `RunLoop.resume(config, history)` rebuilds the loop by replaying ask/tell without evaluating.
    Spans (a worker evolving generations itself from a GAState) are paper-ga only: a non-GA
    loop refuses a state past generation 0.
    """

    def __init__(self, config: RunConfig, state: GAState | None = None) -> None:
        self.config = config
        self.params = GAParams.from_config(config)
        self.layout = layout(config.network_spec)
        self.state = init(self.layout, self.params) if state is None else state
        if self.state.n_weights != self.layout.n_weights:
            raise ValueError(
                f"GA state of {self.state.n_weights} weights for a "
                f"{self.layout.n_weights}-weight network"
            )
        self._strategy = make_strategy(config, self.layout)
        if self._strategy is not None and self.state.generation > 0:
            raise ValueError(
                f"a {config.strategy} run resumes from its history (RunLoop.resume), "
                "not from a GA state"
            )
        self._first = self.state.generation
        self._fitness: list[np.ndarray] = []
        self._descriptors: list[np.ndarray] = []
        self._asked: np.ndarray | None = None
        self._steps: _Steps | None = None
        """The steps a fork took, while this loop follows them (`fork`)."""
        self._forked = False
        """This loop is a fork: it records its steps for the loop it was forked from."""

    @classmethod
    def resume(cls, config: RunConfig, history: StrategyHistory) -> RunLoop:
        """The loop of `config` after the generations of `history`, replayed (no evaluation):
        bit-identical to the loop that was told them, for every strategy."""
        if history.fitness.shape[1:] != (config.population,):
            raise ValueError(
                f"history of {history.fitness.shape[1:]} individuals for a population of "
                f"{config.population}"
            )
        if history.fitness.shape[0] > config.generations:
            raise ValueError(
                f"history of {history.fitness.shape[0]} generations for a run of "
                f"{config.generations}"
            )
        loop = cls(config)
        for fitness, descriptors in zip(history.fitness, history.descriptors, strict=True):
            loop.tell(fitness, None, descriptors)
        return loop

    def fork(self) -> RunLoop:
        """A paper-ga loop at this one's state that records the steps it takes (the genomes
        asked, the state each fitness told gives): once this loop is told the same fitness
        from the same state, it takes those steps instead of computing them again, bit for
        bit the same. The server's spot-check follows a span's claimed fitness on a fork, then
        tells the run's loop the same generations. ValueError for another strategy."""
        if self._strategy is not None:
            raise ValueError(f"a {self.config.strategy} loop cannot be forked")
        fork = RunLoop(self.config, state=self.state)
        fork._asked = self._asked
        fork._forked = True
        fork._steps = self._steps = _Steps()
        return fork

    @property
    def history(self) -> StrategyHistory:
        """Fitness and descriptors told so far (what `resume` takes); a paper-ga loop built
        from a later GAState has none (ValueError): its state is `state`."""
        if self._first != 0:
            raise ValueError(f"this loop started at generation {self._first}: no full history")
        n, d = self.config.population, len(DESCRIPTORS)
        if not self._fitness:
            return StrategyHistory(np.empty((0, n)), np.empty((0, n, d)))
        return StrategyHistory(np.stack(self._fitness), np.stack(self._descriptors))

    @property
    def generation(self) -> int:
        """The generation `ask` gives and `tell` expects."""
        return self.state.generation

    @property
    def done(self) -> bool:
        return self.state.generation >= self.config.generations

    def ask(self) -> np.ndarray:
        """(population, n_weights) genomes of the current generation, read-only (asked once)."""
        if self.done:
            raise ValueError(f"the run is over after {self.config.generations} generations")
        if self._asked is None:
            taken = self._taken_ask()
            if taken is not None:
                genomes = taken
            elif self._strategy is None:
                genomes, _ = ask(
                    ga_rng(self.config.seed, self.generation), self.state, self.params, self.layout
                )
            else:
                genomes = np.ascontiguousarray(self._strategy.ask(self.generation))
            genomes.flags.writeable = False
            self._asked = genomes
            if self._forked and self._steps is not None:
                self._steps.asked[id(self.state)] = (self.state, genomes)
        return self._asked

    def tell(
        self,
        fitness: np.ndarray,
        components: np.ndarray | None = None,
        descriptors: np.ndarray | None = None,
    ) -> Told:
        """Rank the current generation by `fitness` and move on to the next. map-elites,
        cma-me and novelty need `descriptors` (ValueError without them)."""
        genomes = self.ask()
        before = self.state
        key = (id(before), np.asarray(fitness, dtype=np.float64).tobytes())
        taken = self._taken_tell(key)
        if taken is not None:
            self.state, metrics = taken
        else:
            self.state, metrics = tell(genomes, fitness, before, self.params)
            if self._forked and self._steps is not None:
                self._steps.told[key] = (before, self.state, metrics)
        n, d = self.config.population, len(DESCRIPTORS)
        told_descriptors = (
            np.full((n, d), np.nan)
            if descriptors is None
            else np.asarray(descriptors, dtype=np.float64)
        )
        if told_descriptors.shape != (n, d):
            raise ValueError(f"descriptors must be ({n}, {d}), got {told_descriptors.shape}")
        if self._strategy is not None:
            try:
                self._strategy.tell(genomes, np.asarray(fitness), descriptors)
            except ValueError:
                self.state = before  # the generation was not told: it may be told again
                raise
        self._asked = None
        self._fitness.append(np.array(fitness, dtype=np.float64))
        self._descriptors.append(told_descriptors.copy())
        return Told(
            before.generation,
            genomes,
            np.asarray(fitness),
            components,
            descriptors,
            before,
            self.state,
            metrics,
        )

    def _taken_ask(self) -> np.ndarray | None:
        """The genomes a fork asked from this loop's state, while this loop follows its steps
        (the first step it did not take ends the following, freeing what it recorded)."""
        if self._forked or self._steps is None:
            return None
        found = self._steps.asked.pop(id(self.state), None)
        if found is None or found[0] is not self.state:
            self._steps = None
            return None
        return found[1]

    def _taken_tell(self, key: tuple[int, bytes]) -> tuple[GAState, TellMetrics] | None:
        """The state and metrics a fork's `tell` of the same fitness from this loop's state
        gave (`_taken_ask`'s rules)."""
        if self._forked or self._steps is None:
            return None
        found = self._steps.told.pop(key, None)
        if found is None or found[0] is not self.state:
            self._steps = None
            return None
        return found[1], found[2]

    def archive(self) -> Archive | None:
        """The archive of a map-elites, cma-me or novelty run (descriptors (m, 2) on
        `strategy_settings.axes`, fitness (m,), genomes (m, w)); None for paper-ga and CMA-ES."""
        return None if self._strategy is None else self._strategy.archive()

    def candidates(self, genomes: np.ndarray, fitness: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the champion is chosen from, given the final generation's genomes and fitness:
        that generation for paper-ga and CMA-ES, the archive's elites for map-elites and
        cma-me (a QD run's product is its archive), the archive and the final generation for
        novelty (its generations are selected on novelty, not fitness). Rank them with
        `ga.rank` and pass them to `champion`."""
        archive = self.archive()
        if archive is None:
            return np.asarray(genomes), np.asarray(fitness)
        if self.config.strategy == "novelty":
            return (
                np.concatenate([archive.genomes, np.asarray(genomes)]),
                np.concatenate([archive.fitness, np.asarray(fitness)]),
            )
        return archive.genomes, archive.fitness


@dataclass(frozen=True)
class Told:
    """One generation evaluated and told: what a store writes of it."""

    generation: int
    genomes: np.ndarray
    """(population, n_weights) in ask() order."""
    fitness: np.ndarray
    components: np.ndarray | None
    """(population, trials, 4), when the evaluator reported them."""
    descriptors: np.ndarray | None
    """(population, 4) in `evaluate.DESCRIPTORS` order, when the evaluator reported them."""
    before: GAState
    """The state the generation was asked from."""
    after: GAState
    """The state its `tell` gave (the next generation is asked from it)."""
    metrics: TellMetrics

    def summary(self) -> GenerationSummary:
        m = self.metrics
        return GenerationSummary(self.generation, m.best, m.mean, m.worst, m.nan_count)


def evolve(
    config: RunConfig,
    *,
    on_generation: Callable[[GenerationSummary], None] | None = None,
    threads: int | None = None,
) -> EvolutionResult:
    """Run the whole experiment of `config` in this process; a pure function of the config.

    Generations and the champion's validation are simulated on `threads` threads (None: every
    core available, `evaluate.available_cores`); the result does not depend on the count.
    """
    threads = available_cores() if threads is None else threads
    loop = RunLoop(config)
    history: list[GenerationSummary] = []
    told: Told | None = None
    components = np.empty(0)
    while not loop.done:
        fitness, components, descriptors = evaluate_population(
            config, loop.generation, loop.ask(), threads=threads
        )
        told = loop.tell(fitness, components, descriptors)
        history.append(told.summary())
        if on_generation is not None:
            on_generation(history[-1])
    if told is None:
        raise ValueError("a run needs at least one generation")
    genomes, fitness = loop.candidates(told.genomes, told.fitness)
    best = champion(
        config, genomes, fitness, rank(fitness), generation=told.generation, threads=threads
    )
    return EvolutionResult(
        loop.state,
        tuple(history),
        best,
        told.genomes,
        told.fitness,
        components,
        loop.archive(),
    )
