"""Local evolution: the run loop every role composes identically, and its fixed job slices.

A generation is cut into contiguous jobs that depend on the config only (never on how many
workers exist), so a run evaluated in one process or on many gives the same fitness arrays.
"""

from __future__ import annotations


def job_slices(population: int, job_size: int) -> list[tuple[int, int]]:
    """Contiguous [start, stop) slices of `job_size` covering 0..population, in order."""
    if population < 1:
        raise ValueError(f"population must be >= 1, got {population}")
    if job_size < 1:
        raise ValueError(f"job_size must be >= 1, got {job_size}")
    return [(a, min(a + job_size, population)) for a in range(0, population, job_size)]
