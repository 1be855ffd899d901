"""A finished run's champion, chosen by jobs that workers take, sliced like generations.

Once a run's last generation is told, its champion (`evorobotics.evolution.champion`) is
computed in stages: `validate` scores the candidates on the validation set, then `test` runs
the pick's held-out test (either is skipped when the run's validation turns it off). Each
stage's rows are independent (a candidate, a test pose), so however the scheduler slices them
and whoever simulates them, they assemble to `champion`'s document bit for bit; the server
only ranks, picks and writes the document.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evorobotics.evolution import (
    HeldOutTrials,
    RunLoop,
    Told,
    Validated,
    champion_document,
    held_out_score,
    validation_pick,
)
from evorobotics.ga import rank
from schemas.run import RunConfig
from schemas.wire import Stage
from server.runs.outbox import Written


@dataclass
class Choosing:
    """The champion of a run's told last generation being chosen: its candidates (`RunLoop
    .candidates`: the final generation or an archive) ranked on training, the stage in hand
    and what the stages before scored."""

    config: RunConfig
    run_id: int
    told: Told
    genomes: np.ndarray
    fitness: np.ndarray
    order: np.ndarray
    stage: Stage | None
    """The stage in hand; None once the document can be written."""
    stored: bool = False
    """The last generation is in the store already (`Written.stored`)."""
    scored: Validated | None = None
    test: HeldOutTrials | None = None

    @classmethod
    def new(cls, run_id: int, loop: RunLoop, told: Told, *, stored: bool = False) -> Choosing:
        """The choice of `loop`'s champion after its last generation, `told`. ValueError if
        it has no candidate (an empty archive)."""
        config = loop.config
        genomes, fitness = (np.asarray(a) for a in loop.candidates(told.genomes, told.fitness))
        if len(genomes) == 0:
            raise ValueError("no candidate to choose a champion from")
        v = config.validation
        first: Stage | None = "validate" if v.poses else "test" if v.test_poses else None
        return cls(config, run_id, told, genomes, fitness, rank(fitness), first, stored)

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
        """The stage in hand is scored, every row of it (`Result.scores` in row order): on
        to the next. ValueError for a row not scored (NaN) or a stage already over."""
        if self.stage is None:
            raise ValueError(f"run {self.run_id}'s champion has no stage left to score")
        if scores.shape[0] != self.size or not np.isfinite(scores).all():
            raise ValueError(f"run {self.run_id}'s {self.stage} stage is not scored whole")
        if self.stage == "validate":
            self.scored = Validated.from_scores(scores)
            self.stage = "test" if self.config.validation.test_poses else None
        else:
            self.test = HeldOutTrials.from_scores(scores)
            self.stage = None

    def written(self) -> Written:
        """The last generation with the champion's document for the store (all stages
        scored): the document is `champion`'s, bit for bit."""
        if self.stage is not None:
            raise ValueError(f"run {self.run_id}'s champion is still in its {self.stage} stage")
        test = None if self.test is None else held_out_score(self.config, self.test)
        document = champion_document(
            self.config,
            self.genomes,
            self.fitness,
            self.order,
            self.scored,
            test,
            generation=self.told.generation,
            run=self.run_id,
        )
        return Written(self.run_id, self.config, self.told, document, self.stored)
