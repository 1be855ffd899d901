"""The validated champion: chosen on poses no training trial used, and reproducible."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.document import ControllerDocument
from evorobotics.errors import ControllerDocumentError
from evorobotics.evaluate import draw_gap, start_poses, validation_set
from evorobotics.evolution import (
    HeldOutTrials,
    RunLoop,
    Validated,
    best_document,
    champion,
    champion_document,
    evaluate_population,
    evolve,
    held_out,
    held_out_score,
    held_out_trials,
    validate,
)
from evorobotics.explore import confined
from evorobotics.maze import load_maze
from evorobotics.seeds import Purpose
from evorobotics.sim import simulate
from schemas.run import RunConfig, ValidationConfig

SMALL = RunConfig(
    population=10,
    generations=3,
    steps=20,
    seed=4,
    validation=ValidationConfig(poses=12, steps=150, candidates=6),
)


def _final(config: RunConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    loop = RunLoop(config)
    while True:
        told = loop.tell(*evaluate_population(config, loop.generation, loop.ask()))
        if loop.done:
            return told.genomes, told.fitness, told.metrics.order, told.generation


def test_validation_poses_are_never_training_poses() -> None:
    poses, gap = validation_set(SMALL)
    assert poses.shape == (12, 3) and gap is not None and gap.whisker_range.shape == (12, 5)
    assert validation_set(SMALL.model_copy(update={"reality_gap": "off"}))[1] is None
    maze = load_maze(SMALL.maze)
    for generation in range(SMALL.generations + 1):
        training = start_poses(maze, SMALL.seed, generation, 50, SMALL.world)
        assert not (poses[:, None, :] == training[None, :, :]).all(axis=2).any()


def test_the_champion_roams_most_among_the_candidates() -> None:
    genomes, fitness, order, generation = _final(SMALL)
    doc = champion(SMALL, genomes, fitness, order, generation=generation, run=9)
    scored = validate(SMALL, genomes[order[:6]])
    v = doc.validation
    assert v is not None and v.candidates == 6 and (v.poses, v.steps) == (12, 150)
    rank = v.training_rank
    assert scored.roaming[rank] == scored.roaming.max()
    best_score = scored.score[scored.roaming == scored.roaming.max()].max()
    assert scored.score[rank] == best_score
    assert (v.score, v.stuck, v.roaming) == (
        scored.score[rank],
        scored.stuck[rank],
        scored.roaming[rank],
    )
    assert np.array_equal(doc.weights, genomes[order[rank]])
    assert doc.fitness == fitness[order[rank]]
    assert doc.provenance == {"seed": 4, "generation": 2, "rank": rank, "run": 9}
    assert doc.world == SMALL.world


def test_evolve_exports_the_champion_and_is_reproducible() -> None:
    a, b = evolve(SMALL), evolve(SMALL)
    assert a.best.to_json() == b.best.to_json() and a.best.validation is not None
    genomes, fitness, order, generation = _final(SMALL)
    assert a.best == champion(SMALL, genomes, fitness, order, generation=generation)


def test_validation_off_or_one_candidate_is_training_rank_zero() -> None:
    genomes, fitness, order, generation = _final(SMALL)
    off = SMALL.model_copy(update={"validation": ValidationConfig(poses=0)})
    doc = champion(off, genomes, fitness, order, generation=generation)
    test = held_out(off, genomes[order[0]])
    assert doc == best_document(off, genomes, fitness, order, generation=generation, test=test)
    assert doc.validation is None
    one = SMALL.model_copy(update={"validation": ValidationConfig(poses=5, candidates=1)})
    only = champion(one, genomes, fitness, order, generation=generation)
    assert np.array_equal(only.weights, genomes[order[0]])
    assert only.validation is not None and only.validation.training_rank == 0


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**31), gap=st.sampled_from(["on", "off"]))
def test_a_candidates_score_does_not_depend_on_its_batch(seed: int, gap: str) -> None:
    config = SMALL.model_copy(update={"seed": seed, "reality_gap": gap})
    genomes = RunLoop(config).ask()[:4]
    together = validate(config, genomes)
    for i in range(4):
        alone = validate(config, genomes[i : i + 1])
        assert alone.score[0] == together.score[i]
        assert alone.roaming[0] == together.roaming[i] and alone.stuck[0] == together.stuck[i]
    assert ((together.roaming >= 0) & (together.roaming + together.stuck <= 1 + 1e-12)).all()


def test_the_champion_document_round_trips_and_refuses_a_forged_score() -> None:
    genomes, fitness, order, generation = _final(SMALL)
    doc = champion(SMALL, genomes, fitness, order, generation=generation)
    back = ControllerDocument.from_json(doc.to_json())
    assert back == doc and back.validation == doc.validation and back.world == SMALL.world
    assert ControllerDocument(doc.spec, doc.weights).sha256 == doc.sha256  # not hashed
    forged = doc.to_dict()
    forged["validation"]["roaming"] = 2.0
    with pytest.raises(ControllerDocumentError, match="validation"):
        ControllerDocument.from_dict(forged)


def test_the_champions_test_is_held_out_and_what_it_says() -> None:
    """The test's poses and worlds are no training or validation trial's, and its figures are
    the champion's own trials from them, nominal and under the gap, with their intervals."""
    genomes, fitness, order, generation = _final(SMALL)
    config = SMALL.model_copy(
        update={"validation": ValidationConfig(poses=12, steps=150, candidates=6, test_poses=30)}
    )
    doc = champion(config, genomes, fitness, order, generation=generation)
    test = doc.test
    assert test is not None and (test.poses, test.steps, test.seed) == (30, 150, SMALL.seed)
    maze = load_maze(config.maze)
    poses = start_poses(maze, config.seed, 0, 30, config.world, Purpose.TEST)
    chosen_on = [validation_set(config)[0]] + [
        start_poses(maze, config.seed, g, 50, config.world) for g in range(config.generations + 1)
    ]
    for other in chosen_on:
        assert not (poses[:, None, :] == other[None, :, :]).all(axis=2).any()
    gap = draw_gap(config.seed, 0, 30, config.world, Purpose.TEST_GAP, 150)
    chosen_gap = validation_set(config)[1]
    assert chosen_gap is not None
    assert not np.isin(gap.whisker_range, chosen_gap.whisker_range).any()
    for figures, drawn in ((test.nominal, None), (test.gap, gap)):
        w = np.repeat(doc.weights[None], 30, axis=0)
        run = simulate(config.network_spec, w, maze, poses, 150, config.world, drawn, record=True)
        assert run.poses is not None
        roaming = ~confined(run.poses, run.stuck_step) & ~run.stuck
        assert figures.roaming.value == roaming.mean() and figures.stuck.value == run.stuck.mean()
        assert figures.max_offset == pytest.approx(run.max_offset.mean())
        for p in (figures.roaming, figures.stuck):
            assert 0.0 <= p.low <= p.value <= p.high <= 1.0 and p.high - p.low > 0.05
    assert champion(config, genomes, fitness, order, generation=generation, threads=3) == doc
    back = ControllerDocument.from_json(doc.to_json())
    assert back.test == test
    forged = doc.to_dict()
    forged["test"]["gap"]["roaming"]["value"] = 1.5
    with pytest.raises(ControllerDocumentError, match="test"):
        ControllerDocument.from_dict(forged)
    off = config.model_copy(update={"validation": ValidationConfig(poses=12, test_poses=0)})
    assert champion(off, genomes, fitness, order, generation=generation).test is None


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**31), cuts=st.sets(st.integers(1, 11), max_size=4))
def test_the_champion_assembled_from_slices_is_the_champion(seed: int, cuts: set[int]) -> None:
    """Candidates validated in any slices and the test's poses run in any slices (what jobs on
    workers do) give the champion `champion` computes in one call, bit for bit."""
    config = SMALL.model_copy(
        update={
            "seed": seed,
            "reality_gap": "on",
            "validation": ValidationConfig(poses=5, steps=100, candidates=6, test_poses=12),
        }
    )
    genomes, fitness, order, generation = _final(config)
    candidates = genomes[order[:6]]
    bounds = [0, *sorted(c for c in cuts if c < 6), 6]
    parts = [validate(config, candidates[a:b]) for a, b in itertools.pairwise(bounds)]
    scored = Validated(
        *(np.concatenate([getattr(p, f) for p in parts]) for f in ("score", "stuck", "roaming"))
    )
    whole = champion(config, genomes, fitness, order, generation=generation)
    pick = int(whole.provenance["rank"] or 0)
    poses = [0, *sorted(cuts), 12]
    trials = HeldOutTrials.concatenate(
        [held_out_trials(config, genomes[order[pick]], a, b) for a, b in itertools.pairwise(poses)]
    )
    test = held_out_score(config, trials)
    assembled = champion_document(
        config, genomes, fitness, order, scored, test, generation=generation
    )
    assert assembled.to_json() == whole.to_json()
    with pytest.raises(ValueError, match="outside"):
        held_out_trials(config, genomes[0], 3, 13)
