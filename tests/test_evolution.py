"""Local evolution: job slices and the shared run loop."""

from itertools import pairwise

import pytest
from hypothesis import given
from hypothesis import strategies as st

from evorobotics.evolution import job_slices


@given(population=st.integers(1, 5000), job_size=st.integers(1, 600))
def test_job_slices_partition_population_in_order(population: int, job_size: int) -> None:
    slices = job_slices(population, job_size)
    assert slices[0][0] == 0
    assert slices[-1][1] == population
    for (a, b), (c, _) in pairwise(slices):
        assert b == c
        assert b - a == job_size  # only the last slice may be short
    assert all(0 < b - a <= job_size for a, b in slices)
    assert len(slices) == -(-population // job_size)


def test_job_slices_examples() -> None:
    assert job_slices(100, 25) == [(0, 25), (25, 50), (50, 75), (75, 100)]
    assert job_slices(10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert job_slices(3, 50) == [(0, 3)]


@pytest.mark.parametrize(("population", "job_size"), [(0, 5), (-1, 5), (10, 0), (10, -3)])
def test_job_slices_reject_bad_arguments(population: int, job_size: int) -> None:
    with pytest.raises(ValueError, match="must be >= 1"):
        job_slices(population, job_size)
