"""Statistics of a study: per-condition summaries, pairwise tests and one-line verdicts.

A claim about conditions (time delays vs reactive, one GA setting vs another) rests on many
seeds per condition, so a study reports, per condition and metric, the median with its
interquartile range and a bootstrap 95 % confidence interval, and, between every pair of
conditions, a two-sided Mann-Whitney U test (no normality assumed: fitness and exploration
figures are skewed and bounded) with the Vargha-Delaney A12 effect size, the p-values
Holm-corrected over all the comparisons of one call (many metrics x many pairs).

The confidence interval is the percentile bootstrap of the median (`scipy.stats.bootstrap`),
not BCa: BCa is undefined on a sample whose values are all equal (a metric such as `stuck` is
often 0 for every run) and may exclude the sample median, whereas the percentile interval of
the median always holds it (each resample's median is at most the sample median with
probability >= 1/2, and at least it with probability >= 1/2).

Pure functions: no I/O; the bootstrap draws from a `numpy.random.Generator` seeded by the
caller, so the same input gives the same output.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np

METRICS: dict[str, bool] = {
    "best_fitness": True,
    "validation_score": True,
    "roaming": True,
    "stuck": False,
    "max_offset": True,
    "coverage": True,
    "gap_roaming": True,
    "gap_stuck": False,
}
"""Final metrics of a run -> whether a higher value is better (`stuck` is a failure rate)."""

Z_975 = 1.959963984540054
"""The standard normal's 97.5 % quantile: two-sided 95 % intervals."""


def wilson(successes: int, trials: int) -> tuple[float, float]:
    """The 95 % Wilson score interval of a proportion: unlike the normal approximation it
    stays inside [0, 1] and is not empty at 0 or all successes (a champion stuck 0 times)."""
    if trials < 1 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials >= 1, got {successes} of {trials}")
    p = successes / trials
    z2 = Z_975 * Z_975
    centre = (p + z2 / (2 * trials)) / (1 + z2 / trials)
    half = Z_975 * np.sqrt(p * (1 - p) / trials + z2 / (4 * trials * trials)) / (1 + z2 / trials)
    low = 0.0 if successes == 0 else max(0.0, float(centre - half))
    return low, 1.0 if successes == trials else min(1.0, float(centre + half))


MAGNITUDES = ((0.71, "large"), (0.64, "medium"), (0.56, "small"))
"""Vargha-Delaney thresholds on max(A12, 1 - A12); below the last one the effect is negligible."""


@dataclass(frozen=True)
class Summary:
    """One sample of values: its median, quartiles and bootstrap 95 % CI of the median."""

    n: int
    median: float
    q1: float
    q3: float
    ci_low: float
    ci_high: float


@dataclass(frozen=True)
class Comparison:
    """Two conditions on one metric; `a12` is P(a > b) + 0.5 P(a == b) (so 0.5 is no effect).

    `n_a` and `n_b` are the sample sizes tested (NaN dropped), for verdicts that say how much
    data could not tell.
    """

    a: str
    b: str
    metric: str
    u: float
    p_value: float
    p_holm: float
    a12: float
    n_a: int = 0
    n_b: int = 0


def _finite(values: Sequence[float]) -> np.ndarray:
    """The values as floats with NaN (and None) dropped."""
    array = np.asarray(values, dtype=float).ravel()
    finite: np.ndarray = array[~np.isnan(array)]
    return finite


def summarize(values: Sequence[float], *, seed: int = 0, resamples: int = 2000) -> Summary:
    """Median, quartiles and percentile-bootstrap 95 % CI of the median; NaN values dropped.

    Raises ValueError if no value remains or `resamples` < 1. With one value the CI is that value.
    """
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    sample = _finite(values)
    if sample.size == 0:
        raise ValueError("no values to summarize (all NaN or empty)")
    median = float(np.median(sample))
    q1, q3 = (float(q) for q in np.quantile(sample, [0.25, 0.75]))
    if sample.size < 2:
        return Summary(1, median, q1, q3, median, median)
    from scipy import stats as scipy_stats  # 1.5 s of imports: only when statistics are asked

    interval = scipy_stats.bootstrap(
        (sample,),
        np.median,
        n_resamples=resamples,
        vectorized=True,
        method="percentile",
        rng=np.random.default_rng(seed),
    ).confidence_interval
    return Summary(int(sample.size), median, q1, q3, float(interval.low), float(interval.high))


def a12(a: Sequence[float], b: Sequence[float]) -> float:
    """Vargha-Delaney A12: P(x > y) + 0.5 P(x == y) for x drawn from `a`, y from `b`.

    Raises ValueError if either sample is empty after dropping NaN.
    """
    x, y = _finite(a), _finite(b)
    if x.size == 0 or y.size == 0:
        raise ValueError("A12 needs at least one value in each sample")
    return _a12(x, y)


def _a12(x: np.ndarray, y: np.ndarray) -> float:
    """A12 of two non-empty NaN-free samples, from exact integer counts (so A12(x, x) == 0.5)."""
    greater = int(np.count_nonzero(x[:, None] > y[None, :]))
    ties = int(np.count_nonzero(x[:, None] == y[None, :]))
    return (2 * greater + ties) / (2 * x.size * y.size)


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm step-down adjusted p-values, in the input's order (each >= its raw p, <= 1)."""
    raw = np.asarray(p_values, dtype=float)
    count = raw.size
    order = np.argsort(raw, kind="stable")
    scaled = np.minimum(1.0, raw[order] * (count - np.arange(count)))
    adjusted = np.empty(count)
    adjusted[order] = np.maximum.accumulate(scaled) if count else scaled
    return [float(p) for p in adjusted]


def compare(samples: Mapping[str, Mapping[str, Sequence[float]]]) -> list[Comparison]:
    """Mann-Whitney U (two-sided) and A12 for every pair of conditions x shared metric.

    `samples[condition][metric]` holds one value per run. Pairs come in the mapping's order
    (a before b), metrics in a's order; a metric is compared when both conditions have >= 2
    non-NaN values of it. p-values are Holm-corrected over all comparisons returned.
    """
    from scipy import stats as scipy_stats

    tested: list[tuple[str, str, str, float, float, float, int, int]] = []
    for a, b in combinations(samples, 2):
        for metric, values in samples[a].items():
            if metric not in samples[b]:
                continue
            x, y = _finite(values), _finite(samples[b][metric])
            if x.size < 2 or y.size < 2:
                continue
            result = scipy_stats.mannwhitneyu(x, y, alternative="two-sided")
            p_value = float(result.pvalue)
            # Identical constant samples give no rank variance: no evidence of a difference.
            tested.append(
                (
                    a,
                    b,
                    metric,
                    float(result.statistic),
                    1.0 if np.isnan(p_value) else p_value,
                    _a12(x, y),
                    int(x.size),
                    int(y.size),
                )
            )
    corrected = holm([row[4] for row in tested])
    return [
        Comparison(a, b, metric, u, p, p_holm, effect, n_a, n_b)
        for (a, b, metric, u, p, effect, n_a, n_b), p_holm in zip(tested, corrected, strict=True)
    ]


def magnitude(a12_value: float) -> str:
    """Vargha-Delaney magnitude of an A12, symmetric about 0.5: negligible/small/medium/large."""
    effect = round(max(a12_value, 1.0 - a12_value), 9)  # 1 - 0.36 must count as 0.64
    return next((name for threshold, name in MAGNITUDES if effect >= threshold), "negligible")


def verdicts(comparisons: Sequence[Comparison], *, alpha: float = 0.05) -> list[str]:
    """One line per pair of conditions: who wins on which metrics, or that the data cannot tell.

    A condition wins a metric when p_holm < alpha and its values are better in the metric's
    direction (`METRICS`; a metric outside it counts higher as better). A12 is quoted as in the
    comparison, P(a > b) for the line's "a vs b".
    """
    pairs: dict[tuple[str, str], list[Comparison]] = {}
    for comparison in comparisons:
        pairs.setdefault((comparison.a, comparison.b), []).append(comparison)
    lines = []
    for (a, b), group in pairs.items():
        wins: dict[str, list[str]] = {a: [], b: []}
        unclear = []
        for c in group:
            if c.p_holm >= alpha or c.a12 == 0.5:
                unclear.append(c.metric)
                continue
            higher_better = METRICS.get(c.metric, True)
            winner = a if (c.a12 > 0.5) == higher_better else b
            wins[winner].append(
                f"{c.metric} ({'higher' if higher_better else 'lower'}; A12 = {c.a12:.2f}, "
                f"{magnitude(c.a12)}, p_holm = {c.p_holm:.2g})"
            )
        sizes = ", ".join(sorted({f"{c.n_a} vs {c.n_b}" for c in group}))
        if not wins[a] and not wins[b]:
            lines.append(f"{a} vs {b}: the data cannot tell (n = {sizes})")
            continue
        parts = [f"{name} wins on {', '.join(won)}" for name, won in wins.items() if won]
        if unclear:
            parts.append(f"no clear difference on {', '.join(unclear)}")
        lines.append(f"{a} vs {b}: {'; '.join(parts)} (n = {sizes})")
    return lines
