"""A finished run's champion, chosen by jobs that workers take, sliced like generations.

Once a run's last generation is told, its champion (`evorobotics.evolution.champion`) is
computed in stages: `validate` scores the candidates on the validation set, `test` runs the
pick's held-out test. Each stage's slices are independent (a candidate, a test pose), so they
assemble to `champion`'s document bit for bit wherever they were simulated; the server only
ranks, picks and writes the document.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evorobotics.document import ControllerDocument
from evorobotics.evolution import (
    HeldOutTrials,
    Told,
    Validated,
    champion_document,
    held_out_score,
    validation_pick,
)
from evorobotics.ga import rank
from schemas.run import RunConfig
from schemas.wire import Stage


@dataclass
class Choosing:
    """The champion of a run's told last generation being chosen: its candidates (`RunLoop
    .candidates`: the final generation or an archive), the stage in hand and what the stages
    before scored."""

    config: RunConfig
    run_id: int
    told: Told
    genomes: np.ndarray
    fitness: np.ndarray
    order: np.ndarray
    stage: Stage | None
    """The stage in hand; None once the document can be written."""
    scored: Validated | None = None
    test: HeldOutTrials | None = None

    @classmethod
    def new(
        cls, config: RunConfig, run_id: int, told: Told, genomes: np.ndarray, fitness: np.ndarray
    ) -> Choosing:
        v = config.validation
        first: Stage | None = "validate" if v.poses else "test" if v.test_poses else None
        genomes, fitness = np.asarray(genomes), np.asarray(fitness)
        return cls(config, run_id, told, genomes, fitness, rank(fitness), first)

    @property
    def size(self) -> int:
        """Rows of the stage in hand: candidates validated, or test poses."""
        v = self.config.validation
        if self.stage == "validate":
            return min(v.candidates, len(self.genomes))
        return v.test_poses if self.stage == "test" else 0

    def genomes_for(self, start: int, stop: int) -> np.ndarray:
        """A job's genomes: candidates start:stop (validate), or the pick alone (test)."""
        if self.stage == "validate":
            return np.asarray(self.genomes[self.order[start:stop]])
        pick = 0 if self.scored is None else validation_pick(self.scored)
        return np.asarray(self.genomes[int(self.order[pick])][None])

    def advance(self, scores: np.ndarray) -> None:
        """The stage in hand is scored (every row of it, `Result.scores`): on to the next."""
        v = self.config.validation
        if self.stage == "validate":
            self.scored = Validated.from_scores(scores)
            self.stage = "test" if v.test_poses else None
        elif self.stage == "test":
            self.test = HeldOutTrials.from_scores(scores)
            self.stage = None

    def document(self) -> ControllerDocument:
        """The champion's document (all stages scored): `champion`'s, bit for bit."""
        if self.stage is not None:
            raise ValueError(f"run {self.run_id}'s champion is still in its {self.stage} stage")
        test = None if self.test is None else held_out_score(self.config, self.test)
        return champion_document(
            self.config,
            self.genomes,
            self.fitness,
            self.order,
            self.scored,
            test,
            generation=self.told.generation,
            run=self.run_id,
        )
