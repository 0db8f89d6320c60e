"""Statistics over training seeds, and a paired test of two methods on the same queries.

PoseNet re-implementations are known for numbers that move from one training run to
the next, so a comparison is only worth reading with the spread over seeds and a
test on the per-query errors, which are paired (both methods answer the same queries
with models trained from the same seeds).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.stats import rankdata, spearmanr, wilcoxon

from relocfw.report.metrics import failed_as_infinite

SIGNIFICANCE = 0.05
BOOTSTRAP_RESAMPLES = 2000
# The verdict where the difference itself is undefined: the method's median is
# infinite on one seed and the reference's on another, and the mean of +inf and -inf
# is no number. Reading that as "no difference" would hide two collapsed runs.
UNDEFINED = "undefined (each side's median is infinite on a different seed)"


def interval_undefined(undefined: int, resamples: int) -> str:
    """The verdict where the observed difference is a number but a bound of its
    interval is not: "interval undefined (792 of 2000 resamples undefined)".

    Such a bound is infinite only because undefined resamples fill its tail; an
    interval of [-inf, inf] would otherwise read as "no significant difference".
    """
    return f"interval undefined ({undefined} of {resamples} resamples undefined)"


def spread(values: Sequence[float]) -> dict[str, float | list[float]]:
    """Mean, sample standard deviation (0 for one value), minimum and maximum."""
    array = np.asarray(values, dtype=np.float64)
    with np.errstate(invalid="ignore"):  # a failed seed (inf) has an undefined std: NaN
        std = float(array.std(ddof=1)) if len(array) > 1 else 0.0
    return {
        "values": array.tolist(),
        "mean": float(array.mean()),
        "std": std,
        "min": float(array.min()),
        "max": float(array.max()),
    }


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman rank correlation; NaN where it is undefined (n < 2 or a constant side).

    Infinite errors rank last, as the worst; NaN distances make it NaN.
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if len(x) < 2 or np.isnan(x).any() or np.isnan(y).any():
        return float("nan")
    if len(np.unique(x)) < 2 or len(np.unique(y)) < 2:
        return float("nan")
    return float(spearmanr(x, y)[0])


def difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b, with two failures (inf - inf) counted as a tie, not as NaN."""
    both_failed = np.isinf(a) & np.isinf(b) & (np.sign(a) == np.sign(b))
    return np.where(both_failed, 0.0, a - np.where(both_failed, 0.0, b))


def seed_mean(differences: np.ndarray) -> np.ndarray:
    """Mean over seeds (axis 0) of per-seed differences, in the extended reals.

    +inf where some seed's difference is +inf and none is -inf (and the reverse);
    NaN, undefined, where one seed says +inf and another -inf: the method's median is
    infinite on one seed and the reference's on another, and no number sums those.
    """
    with np.errstate(invalid="ignore"):  # inf + -inf: NaN on purpose, read as undefined
        return np.mean(differences, axis=0)


def per_query_differences(errors: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """[N] what the signed-rank test ranks: each query's median over seeds of its
    per-seed paired difference (the method's error minus the reference's, same seed).

    Differencing on each seed first keeps the pairing the bootstrap keeps (the same
    query, the same seed's models); differencing each side's median over seeds would
    compare errors from different seeds once there are three or more. With an even
    number of seeds the median is the midpoint of the middle two, and a midpoint of
    +inf and -inf (the method failed the query on one seed, the reference on another)
    counts as a tie, like two failures on the same seed.
    """
    per_seed = difference(errors, reference)  # [S, N]: no NaN, inputs are never NaN
    with np.errstate(invalid="ignore"):
        medians = np.median(per_seed, axis=0)
    return np.where(np.isnan(medians), 0.0, medians)


def signed_rank_direction(differences: np.ndarray) -> float:
    """Which way the signed-rank test leans: +1 (higher), -1 (lower) or 0.

    Wilcoxon's two-sided p carries no direction; this is the sign of the sum of the
    signed ranks of the non-zero differences (inf ranks last), the quantity it tests.
    """
    nonzero = differences[differences != 0]
    if not len(nonzero):
        return 0.0
    ranks = rankdata(np.abs(nonzero))
    return float(np.sign(np.sum(np.sign(nonzero) * ranks)))


def verdict(
    p_value: float, low: float, high: float, direction: float, alpha: float = SIGNIFICANCE
) -> str:
    """The paired test in words: significant only when both tests find a difference
    in the same direction (the interval's side of zero and the signed ranks' lean).

    An undefined input (a NaN p or bound) gives UNDEFINED, never "no significant
    difference": a NaN compares false with everything, so it would otherwise read as
    an interval that contains zero.
    """
    if np.isnan([p_value, low, high]).any():
        return UNDEFINED
    excludes_zero = low > 0 or high < 0
    side = 1.0 if low > 0 else -1.0
    if p_value < alpha and excludes_zero and direction == side:
        return "significantly higher" if side > 0 else "significantly lower"
    if p_value >= alpha and not excludes_zero:
        return "no significant difference"
    return "inconclusive (the two tests disagree)"


def resampled_median_differences(
    errors: np.ndarray, reference: np.ndarray, picks: np.ndarray, chunk: int = 200
) -> np.ndarray:
    """[R] difference of medians (`seed_mean` over seeds, NaN: undefined) for each row
    of query indices, `chunk` resamples at a time so memory stays at S x chunk x N.

    Both methods take the same rows on every seed: the bootstrap is paired.
    """
    out = []
    for start in range(0, len(picks), chunk):
        rows = picks[start : start + chunk]
        medians = np.median(errors[:, rows], axis=2)  # [S, chunk]
        reference_medians = np.median(reference[:, rows], axis=2)
        out.append(seed_mean(difference(medians, reference_medians)))
    return np.concatenate(out)


def percentile_interval(resampled: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """The bootstrap's central `level` interval, defined even where resamples are not.

    A resample whose difference is undefined (NaN) could lie anywhere, so it counts
    as -inf for the lower bound and as +inf for the upper one: the interval can only
    widen, never shrink, and a bound is infinite once such resamples pass its tail.
    Order statistics (inverted_cdf), never interpolation: between two infinite
    differences (a method failing most queries) interpolation would give NaN.
    """
    undefined = np.isnan(resampled)
    tail = 100 * (1 - level) / 2
    low = np.percentile(np.where(undefined, -np.inf, resampled), tail, method="inverted_cdf")
    high = np.percentile(np.where(undefined, np.inf, resampled), 100 - tail, method="inverted_cdf")
    return float(low), float(high)


def undefined_bounds(resampled: np.ndarray, level: float = 0.95) -> tuple[bool, bool]:
    """Which bounds of `percentile_interval` are infinite only because of undefined
    resamples: (lower, upper).

    A bound is undefined where it is infinite with the undefined resamples on its side
    and finite with them moved to the other end; a few undefined resamples inside
    the tails only widen a bound that stays a number, and a bound that is infinite
    either way (a method failing most queries) is a defined infinity.
    """
    undefined = np.isnan(resampled)
    tail = 100 * (1 - level) / 2
    low_if_high = np.percentile(np.where(undefined, np.inf, resampled), tail, method="inverted_cdf")
    high_if_low = np.percentile(
        np.where(undefined, -np.inf, resampled), 100 - tail, method="inverted_cdf"
    )
    low, high = percentile_interval(resampled, level)
    return bool(low == -np.inf and low_if_high > -np.inf), bool(
        high == np.inf and high_if_low < np.inf
    )


def paired_verdict(
    observed: float,
    resampled: np.ndarray,
    p_value: float,
    direction: float,
    alpha: float = SIGNIFICANCE,
) -> str:
    """The verdict of `paired_test`: UNDEFINED where the observed difference is,
    `interval_undefined` where a bound of its interval is, else `verdict`."""
    if np.isnan(observed):
        return UNDEFINED
    if any(undefined_bounds(resampled)):
        return interval_undefined(int(np.isnan(resampled).sum()), len(resampled))
    low, high = percentile_interval(resampled)
    return verdict(p_value, low, high, direction, alpha)


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
            per query (+inf or NaN: failed).
        reference: [S, N] the reference method's errors on the same seeds and queries.
        seed: of the bootstrap's resampling.

    Returns:
        `median_difference`: the method's median error minus the reference's, averaged
        over seeds (negative: the method is better; NaN where it is undefined, see
        `seed_mean`); `bootstrap_95`: its 95% interval from resampling queries (the
        same queries for every seed and both methods, so the pairing and the seeds
        stay together; see `percentile_interval` for undefined resamples);
        `undefined_resamples`: how many resamples had no defined difference;
        `wilcoxon_p`: the two-sided Wilcoxon signed-rank test of the per-query
        differences, each the median over seeds of the query's per-seed difference
        (`per_query_differences`: paired within each seed, as the bootstrap is; the
        queries are the independent units); `untied_pairs`: the queries with a
        non-zero difference (Wilcoxon drops ties, two failures included);
        `method_better_share`: the share of queries where that difference is
        negative; and `verdict`, the result in words: UNDEFINED where
        `median_difference` is, `interval_undefined` (with the count of undefined
        resamples) where a bound of `bootstrap_95` is infinite only because
        undefined resamples fill its tail (see `undefined_bounds`), never "no
        significant difference" there.

    The test holds the trained models fixed: the bootstrap resamples queries, so
    it says whether these seeds' models differ on this scene, and the spread over
    seeds (reported beside it) says how much training itself moves the medians.
    """
    errors = failed_as_infinite(np.atleast_2d(errors))
    reference = failed_as_infinite(np.atleast_2d(reference))
    if errors.shape != reference.shape:
        raise ValueError(f"paired errors differ in shape: {errors.shape} vs {reference.shape}")
    seeds, queries = errors.shape
    per_query = per_query_differences(errors, reference)
    observed = float(seed_mean(difference(np.median(errors, axis=1), np.median(reference, axis=1))))
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, queries, size=(resamples, queries))
    resampled = resampled_median_differences(errors, reference, picks)
    low, high = percentile_interval(resampled)
    # Identical answers leave nothing to test (Wilcoxon would divide by zero).
    p_value = 1.0 if np.all(per_query == 0) else float(wilcoxon(per_query).pvalue)
    direction = signed_rank_direction(per_query)
    return {
        "seeds": seeds,
        "pairs": queries,
        "median_difference": observed,
        "bootstrap_95": [low, high],
        "undefined_resamples": int(np.isnan(resampled).sum()),
        "wilcoxon_p": p_value,
        "untied_pairs": int(np.count_nonzero(per_query)),  # what Wilcoxon ranks
        "method_better_share": float(np.mean(per_query < 0)),
        "verdict": paired_verdict(observed, resampled, p_value, direction, alpha),
    }
