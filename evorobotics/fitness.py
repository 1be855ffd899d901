"""Eq 12: F = k1 total_curve_length + k2 net_offset + k3 max_offset - k4 stuck.

Distances in metres; stuck is 0 or 1 per trial and is a penalty (the paper writes "+ k4 stuck"
with k4 = 50 meant as a cost; we subtract it so a positive k4 always punishes). A controller's
fitness is the mean of Eq 12 over its trials.
"""

from __future__ import annotations

import numpy as np

from schemas.run import FitnessWeights

COMPONENTS = ("curve_length", "net_offset", "max_offset", "stuck")
"""Order of the last axis of every components array."""


def fitness(components: np.ndarray, weights: FitnessWeights) -> np.ndarray:
    """Eq 12 of each trial: (..., 4) components in COMPONENTS order -> (...,)."""
    if components.shape[-1:] != (4,):
        raise ValueError(f"components must end in an axis of 4, got shape {components.shape}")
    # elementwise, not a matmul: BLAS may round differently by batch size (slicing independence)
    c = np.asarray(components, dtype=np.float64)
    return np.asarray(
        weights.k1 * c[..., 0]
        + weights.k2 * c[..., 1]
        + weights.k3 * c[..., 2]
        - weights.k4 * c[..., 3]
    )


def mean_fitness(components: np.ndarray, weights: FitnessWeights) -> np.ndarray:
    """A controller's fitness: Eq 12 averaged over its trials, (k, trials, 4) -> (k,)."""
    if components.ndim != 3:
        raise ValueError(f"components must be (k, trials, 4), got shape {components.shape}")
    # np.mean's own steps (add.reduce, then true division by the count) minus its Python layer
    total = np.add.reduce(fitness(components, weights), axis=1)
    return np.asarray(total / components.shape[1])
