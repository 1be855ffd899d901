"""Every random draw of a run, derived from (run seed, generation, purpose, index).

A run is a pure function of its config and seed: no global random state, no wall time, no
worker identity. Each consumer asks for its own stream by purpose, so adding a new consumer
never shifts the draws of an existing one.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Purpose(IntEnum):
    """Stable codes of the independent random streams (never renumber: runs depend on them)."""

    INIT = 1
    MUTATION = 2
    START_POSES = 3
    REALITY_GAP = 4
    MAZE = 5
    EVALUATION = 6
    VALIDATION = 7
    VALIDATION_GAP = 8
    EXPLORATION = 9
    EXPLORATION_GAP = 10
    BODY_GAP = 11
    STRATEGY = 12
    TEST = 13
    TEST_GAP = 14
    ROBUSTNESS = 15


def rng(seed: int, generation: int, purpose: Purpose, index: int = 0) -> np.random.Generator:
    """The generator for one (seed, generation, purpose, index); same key, same draws."""
    return np.random.Generator(np.random.PCG64(seed_sequence(seed, generation, purpose, index)))


def seed_sequence(
    seed: int, generation: int, purpose: Purpose, index: int = 0
) -> np.random.SeedSequence:
    """The SeedSequence behind `rng`, for libraries that take one (pyribs archives, emitters)."""
    for name, value in (("seed", seed), ("generation", generation), ("index", index)):
        if value < 0:
            raise ValueError(f"{name} must be >= 0, got {value}")
    return np.random.SeedSequence([seed, generation, int(purpose), index])
