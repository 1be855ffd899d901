"""evorobotics.stats: summaries, Mann-Whitney + A12 comparisons, Holm correction, verdicts."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import mannwhitneyu

from evorobotics.stats import (
    METRICS,
    Comparison,
    a12,
    compare,
    holm,
    magnitude,
    summarize,
    verdicts,
)

# Small integers make ties common, the case that breaks naive A12 and BCa intervals.
values = st.lists(
    st.one_of(st.integers(-5, 5).map(float), st.floats(-1e6, 1e6)), min_size=1, max_size=30
)
p_values = st.lists(st.floats(0.0, 1.0), max_size=40)


@given(values, values)
def test_a12_is_a_probability_and_antisymmetric(a: list[float], b: list[float]) -> None:
    forward, backward = a12(a, b), a12(b, a)
    assert 0.0 <= forward <= 1.0
    assert forward == pytest.approx(1.0 - backward, abs=1e-12)


@given(values)
def test_a12_of_a_sample_with_itself_is_one_half(a: list[float]) -> None:
    assert a12(a, list(a)) == 0.5


def test_a12_known_values() -> None:
    assert a12([1, 2, 3], [1, 2, 3]) == 0.5
    assert a12([4, 5, 6], [1, 2, 3]) == 1.0
    assert a12([1, 2, 3], [4, 5, 6]) == 0.0
    assert a12([1, 2], [2]) == 0.25  # one loss, one tie
    assert a12([1.0, math.nan, 3.0], [2.0]) == 0.5  # NaN dropped
    with pytest.raises(ValueError, match="at least one value"):
        a12([math.nan], [1.0])


@given(p_values)
def test_holm_is_at_least_raw_at_most_one_and_monotone(raw: list[float]) -> None:
    adjusted = holm(raw)
    assert len(adjusted) == len(raw)
    assert all(p <= q <= 1.0 for p, q in zip(raw, adjusted, strict=True))
    ranked = [adjusted[i] for i in sorted(range(len(raw)), key=raw.__getitem__)]
    assert ranked == sorted(ranked)


def test_holm_known_values() -> None:
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    assert holm([0.5, 0.9]) == [1.0, 1.0]
    assert holm([]) == []


@settings(max_examples=60, deadline=None)
@given(values, st.integers(0, 2**32 - 1))
def test_summary_orders_quartiles_median_and_interval(sample: list[float], seed: int) -> None:
    summary = summarize(sample, seed=seed, resamples=200)
    assert summary.n == len(sample)
    assert summary.q1 <= summary.median <= summary.q3
    assert summary.ci_low <= summary.median <= summary.ci_high
    if summary.n == 1:
        assert summary.ci_low == summary.ci_high == summary.median


@settings(max_examples=20, deadline=None)
@given(values, st.integers(0, 2**32 - 1))
def test_summary_is_deterministic_for_a_seed(sample: list[float], seed: int) -> None:
    assert summarize(sample, seed=seed, resamples=300) == summarize(
        sample, seed=seed, resamples=300
    )


def test_summary_known_values_and_nan() -> None:
    summary = summarize([3.0, math.nan, 1.0, 2.0, 4.0, 5.0])
    assert (summary.n, summary.median, summary.q1, summary.q3) == (5, 3.0, 2.0, 4.0)
    assert 1.0 <= summary.ci_low < 3.0 < summary.ci_high <= 5.0
    with pytest.raises(ValueError, match="no values"):
        summarize([math.nan])
    with pytest.raises(ValueError, match="no values"):
        summarize([])


def test_summary_of_a_constant_sample_is_that_constant() -> None:
    summary = summarize([0.0] * 20)
    assert (summary.n, summary.median, summary.ci_low, summary.ci_high) == (20, 0.0, 0.0, 0.0)


conditions = st.dictionaries(
    st.sampled_from(["paper-best", "reactive", "recurrent-small", "x"]),
    st.dictionaries(st.sampled_from(list(METRICS)), st.lists(st.floats(0, 10), max_size=6)),
    max_size=4,
)


@settings(max_examples=60, deadline=None)
@given(conditions)
def test_compare_covers_each_pair_and_shared_metric_once(
    samples: dict[str, dict[str, list[float]]],
) -> None:
    comparisons = compare(samples)
    names = list(samples)
    expected = [
        (a, b, metric)
        for i, a in enumerate(names)
        for b in names[i + 1 :]
        for metric in samples[a]
        if metric in samples[b] and len(samples[a][metric]) >= 2 and len(samples[b][metric]) >= 2
    ]
    assert [(c.a, c.b, c.metric) for c in comparisons] == expected
    assert [c.p_holm for c in comparisons] == holm([c.p_value for c in comparisons])
    for c in comparisons:
        assert 0.0 <= c.p_value <= c.p_holm <= 1.0
        assert c.a12 == a12(samples[c.a][c.metric], samples[c.b][c.metric])
        assert (c.n_a, c.n_b) == (len(samples[c.a][c.metric]), len(samples[c.b][c.metric]))


def test_compare_matches_scipy_mann_whitney() -> None:
    x = [12.5, 30.1, 8.0, 41.2, 25.0, 19.9, 33.3]
    y = [5.1, 7.7, 14.0, 9.9, 3.2, 11.1]
    (comparison,) = compare({"td": {"coverage": x}, "re": {"coverage": y}})
    reference = mannwhitneyu(x, y, alternative="two-sided")
    assert comparison.u == reference.statistic
    assert comparison.p_value == reference.pvalue == comparison.p_holm
    assert (comparison.a, comparison.b, comparison.a12) == ("td", "re", reference.statistic / 42)
    (exact,) = compare({"a": {"m": [1, 2, 3]}, "b": {"m": [4, 5, 6]}})
    assert (exact.u, exact.a12) == (0.0, 0.0)
    assert exact.p_value == pytest.approx(0.1)  # exact test: 2 of C(6, 3) = 20 orderings


def test_compare_of_identical_constant_samples_has_p_one() -> None:
    (comparison,) = compare({"a": {"stuck": [0.0] * 5}, "b": {"stuck": [0.0] * 5}})
    assert (comparison.p_value, comparison.p_holm, comparison.a12) == (1.0, 1.0, 0.5)


def test_verdicts_name_the_winner_in_each_metrics_direction() -> None:
    low, high = [float(i) for i in range(20)], [float(i) for i in range(100, 120)]
    comparisons = compare(
        {
            "delays": {"coverage": high, "stuck": low, "roaming": low},
            "reactive": {"coverage": low, "stuck": high, "roaming": list(low)},
            "same": {"coverage": low},
        }
    )
    lines = verdicts(comparisons)
    assert lines[0] == (
        "delays vs reactive: delays wins on coverage (higher; A12 = 1.00, large, p_holm = 3.4e-07),"
        " stuck (lower; A12 = 0.00, large, p_holm = 3.4e-07); no clear difference on roaming"
        " (n = 20 vs 20)"
    )
    assert lines[1].startswith("delays vs same: delays wins on coverage (higher; A12 = 1.00")
    assert lines[2] == "reactive vs same: the data cannot tell (n = 20 vs 20)"
    assert len(lines) == 3


def test_verdicts_lower_is_better_for_stuck_in_either_position() -> None:
    stuck_more = Comparison("a", "b", "stuck", 90.0, 0.001, 0.01, 0.9, 10, 10)
    assert verdicts([stuck_more]) == [
        "a vs b: b wins on stuck (lower; A12 = 0.90, large, p_holm = 0.01) (n = 10 vs 10)"
    ]
    covers_less = Comparison("a", "b", "coverage", 40.0, 0.001, 0.02, 0.4, 10, 10)
    assert verdicts([covers_less], alpha=0.05) == [
        "a vs b: b wins on coverage (higher; A12 = 0.40, small, p_holm = 0.02) (n = 10 vs 10)"
    ]
    assert verdicts([covers_less], alpha=0.01) == ["a vs b: the data cannot tell (n = 10 vs 10)"]


@pytest.mark.parametrize(
    ("value", "name"),
    [(0.5, "negligible"), (0.559, "negligible"), (0.56, "small"), (0.37, "small"), (0.36, "medium"),
     (0.64, "medium"), (0.3, "medium"), (0.71, "large"), (0.0, "large")],
)  # fmt: skip
def test_magnitude_thresholds_are_symmetric(value: float, name: str) -> None:
    assert magnitude(value) == name
