"""Statistics over training seeds, and a paired test of two methods on the same queries.

PoseNet re-implementations are known for numbers that move from one training run to
the next, so a comparison is only worth reading with the spread over seeds and a
test on the per-query errors, which are paired (both methods answer the same queries
with models trained from the same seeds).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.stats import wilcoxon

SIGNIFICANCE = 0.05
BOOTSTRAP_RESAMPLES = 2000


def spread(values: Sequence[float]) -> dict[str, float | list[float]]:
    """Mean, sample standard deviation (0 for one value), minimum and maximum."""
    array = np.asarray(values, dtype=np.float64)
    return {
        "values": array.tolist(),
        "mean": float(array.mean()),
        "std": float(array.std(ddof=1)) if len(array) > 1 else 0.0,
        "min": float(array.min()),
        "max": float(array.max()),
    }


def difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b, with two failures (inf - inf) counted as a tie, not as NaN."""
    both_failed = np.isinf(a) & np.isinf(b) & (np.sign(a) == np.sign(b))
    return np.where(both_failed, 0.0, a - np.where(both_failed, 0.0, b))


def verdict(p_value: float, low: float, high: float, alpha: float = SIGNIFICANCE) -> str:
    """The paired test in words. Significant only when both tests agree."""
    excludes_zero = low > 0 or high < 0
    if p_value < alpha and excludes_zero:
        return "significantly higher" if low > 0 else "significantly lower"
    if p_value >= alpha and not excludes_zero:
        return "no significant difference"
    return "inconclusive (the two tests disagree)"


def paired_test(
    errors: np.ndarray,
    reference: np.ndarray,
    seed: int = 0,
    resamples: int = BOOTSTRAP_RESAMPLES,
    alpha: float = SIGNIFICANCE,
) -> dict[str, object]:
    """Is a method's error different from the reference's on the same queries?

    Args:
        errors: [S, N] the method's errors, one row per training seed, one column
            per query (+inf: failed).
        reference: [S, N] the reference method's errors on the same seeds and queries.
        seed: of the bootstrap's resampling.

    Returns:
        `median_difference`: the method's median error minus the reference's, averaged
        over seeds (negative: the method is better); `bootstrap_95`: its 95% interval
        from resampling queries (the same queries for every seed and both methods, so
        the pairing and the seeds stay together); `wilcoxon_p`: the two-sided
        Wilcoxon signed-rank test of the per-query differences, each query's error
        being its median over seeds (the queries are the independent units);
        `method_better_share`: the share of queries where the method's error is
        lower; and `verdict`, the result in words.
    """
    errors = np.atleast_2d(np.asarray(errors, dtype=np.float64))
    reference = np.atleast_2d(np.asarray(reference, dtype=np.float64))
    if errors.shape != reference.shape:
        raise ValueError(f"paired errors differ in shape: {errors.shape} vs {reference.shape}")
    seeds, queries = errors.shape
    per_query = difference(np.median(errors, axis=0), np.median(reference, axis=0))
    observed = float(np.mean(difference(np.median(errors, axis=1), np.median(reference, axis=1))))
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, queries, size=(resamples, queries))
    medians = np.median(errors[:, picks], axis=2)  # [S, resamples]
    reference_medians = np.median(reference[:, picks], axis=2)
    resampled = np.mean(difference(medians, reference_medians), axis=0)
    low, high = (float(v) for v in np.percentile(resampled, [2.5, 97.5]))
    # Identical answers leave nothing to test (Wilcoxon would divide by zero).
    p_value = 1.0 if np.all(per_query == 0) else float(wilcoxon(per_query).pvalue)
    return {
        "seeds": seeds,
        "pairs": queries,
        "median_difference": observed,
        "bootstrap_95": [low, high],
        "wilcoxon_p": p_value,
        "method_better_share": float(np.mean(per_query < 0)),
        "verdict": verdict(p_value, low, high, alpha),
    }
