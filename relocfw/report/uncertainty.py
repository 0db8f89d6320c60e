"""How well a method's uncertainty tells good answers from bad ones.

Bayesian PoseNet and test-time sampling give each answer a spread (position spread in
metres, orientation spread in degrees); a pose refiner gives each answer a confidence
(e.g. PnP inliers), which `confidence_uncertainty` turns into an uncertainty that
ranks the same way a spread does. A useful uncertainty ranks queries by their error.
Measured here the way the literature does:

- the Spearman rank correlation of spread with error;
- the sparsification curve: the median error of the queries kept as the most
  uncertain fraction is removed, against the same curve when queries are removed by
  their true error (the oracle); AUSE, the area between the two (0: the spread ranks
  queries exactly as their errors do);
- the median error left after rejecting the 10 / 20 / 30 % most uncertain queries.

Failed queries and missing spreads, one rule each, the same in every measure:

- A query without a spread (NaN) is the most uncertain: it is removed or rejected
  first and ranks with the largest spreads. Nothing vouches for it, and dropping it
  would hide it. The same holds for a NaN confidence.
- A failed query (a NaN or infinite error) is infinitely wrong, as in the accuracy
  metrics: it ranks last in Spearman and counts in the sparsification curve and the
  rejection medians (which are infinite while failures fill half of what is kept).
  AUSE is the exception: it is the area over the queries with a finite error, and
  `failed_queries` says how many were left out. An infinite error would otherwise
  make the area infinite whenever the spread does not put the failure first, which
  says nothing about how the spread ranks the other queries.
"""

from __future__ import annotations

import numpy as np

from relocfw.report.metrics import failed_as_infinite
from relocfw.report.statistics import spearman

REJECTION_SHARES = (0.1, 0.2, 0.3)


def sparsification_curve(errors: np.ndarray, order: np.ndarray) -> np.ndarray:
    """[N] median error of the queries kept after removing the first i of `order`.

    Entry i removes the i queries that come first in `order` (most uncertain first),
    so entry 0 is the median over all queries and entry N-1 keeps one query. A failed
    query (NaN or inf error) is +inf, so an entry is inf while failures fill the upper
    half of the queries kept; never NaN.
    """
    errors = failed_as_infinite(errors)
    kept_last_first = errors[np.asarray(order)][::-1]
    # The median of each suffix of `order`, computed once per length.
    return np.array([np.median(kept_last_first[: len(errors) - i]) for i in range(len(errors))])


def most_uncertain_first(uncertainty: np.ndarray) -> np.ndarray:
    """Query indices from the largest spread to the smallest (stable among ties).

    A NaN spread (none measured) comes first, tied with an infinite one.
    """
    uncertainty = np.asarray(uncertainty, dtype=np.float64)
    uncertainty = np.where(np.isnan(uncertainty), np.inf, uncertainty)
    return np.argsort(-uncertainty, kind="stable")


def ause(errors: np.ndarray, uncertainty: np.ndarray) -> dict[str, object]:
    """Sparsification curves and the area between them, over the answered queries.

    Returns:
        `fractions` removed (i / n, n the queries with a finite error),
        `by_uncertainty` and `oracle` curves over those n queries, and `ause`, the
        mean over fractions of (by_uncertainty - oracle): the area between the curves
        on [0, 1), in the errors' unit. 0 when the spread orders the queries as their
        errors do; largest when it orders them in reverse; NaN when no query has a
        finite error. `failed_queries`: the queries left out (NaN or inf error).
    """
    errors = failed_as_infinite(errors)
    answered = np.isfinite(errors)
    errors = errors[answered]
    uncertainty = np.asarray(uncertainty, dtype=np.float64)[answered]
    by_uncertainty = sparsification_curve(errors, most_uncertain_first(uncertainty))
    oracle = sparsification_curve(errors, most_uncertain_first(errors))
    gap = by_uncertainty - oracle
    return {
        "fractions": (np.arange(len(errors)) / max(len(errors), 1)).tolist(),
        "by_uncertainty": by_uncertainty.tolist(),
        "oracle": oracle.tolist(),
        "ause": float(np.mean(gap)) if len(gap) else float("nan"),
        "failed_queries": int(np.count_nonzero(~answered)),
    }


def rejection_medians(
    errors: np.ndarray, uncertainty: np.ndarray, shares: tuple[float, ...] = REJECTION_SHARES
) -> dict[str, float]:
    """Median error after rejecting each share of the most uncertain queries.

    Failed queries that are kept count as +inf (the median is inf while they fill
    half of what is kept); a NaN spread is rejected first.
    """
    errors = failed_as_infinite(errors)
    order = most_uncertain_first(uncertainty)
    out = {}
    for share in shares:
        rejected = int(round(share * len(errors)))
        kept = order[rejected:] if rejected < len(errors) else order[-1:]
        out[f"{share:.0%}"] = float(np.median(errors[kept]))
    return out


def confidence_uncertainty(confidence: np.ndarray, fell_back: np.ndarray) -> np.ndarray:
    """[N] A refiner's confidence as an uncertainty: the less confident, the larger.

    The uncertainty is -confidence (a confidence is higher for a more trustworthy
    pose), except that every fallback ranks above every accepted answer: a fallback
    answered the network's pose, which the refiner could not confirm, so its inlier
    count says nothing in its favour. Fallbacks are lifted together, keeping their own
    order. Only the ranking matters to the measures here, so the lift's size does not.

    Args:
        confidence: [N] the refiner's confidence per answer; NaN where it has none
            (then NaN here too: the most uncertain, as a missing spread).
        fell_back: [N] True where the refiner fell back to the network's pose.
    """
    uncertainty = -np.array(confidence, dtype=np.float64)
    fell_back = np.asarray(fell_back, dtype=bool)
    # A fallback claiming infinite confidence cannot be ranked among the others: none.
    uncertainty[fell_back & ~np.isfinite(uncertainty)] = np.nan
    accepted = ~fell_back & np.isfinite(uncertainty)
    lifted = fell_back & np.isfinite(uncertainty)
    if accepted.any() and lifted.any():
        # Strictly above the least confident accepted answer (ties would interleave).
        shift = uncertainty[accepted].max() - uncertainty[lifted].min() + 1.0
        uncertainty[lifted] += max(shift, 0.0)
    return uncertainty


def uncertainty_quality(
    position_errors: np.ndarray,
    orientation_errors: np.ndarray,
    position_spread: np.ndarray,
    orientation_spread: np.ndarray,
) -> dict[str, object] | None:
    """Every measure above for position and orientation; None when nothing was sampled.

    The spreads may be any uncertainty (larger: less trusted), e.g. a refiner's
    `confidence_uncertainty` for both kinds. Each kind carries the Spearman
    correlation of uncertainty with error twice: `spearman_uncertainty_error`, and
    `spearman_spread_error`, the name earlier reports read. Each kind also carries
    `failed_queries`, the failures AUSE leaves out (see the module's rules).
    """
    position_spread = np.asarray(position_spread, dtype=np.float64)
    orientation_spread = np.asarray(orientation_spread, dtype=np.float64)
    if np.all(np.isnan(position_spread)):
        return None
    quality: dict[str, object] = {}
    for kind, errors, spread in (
        ("position", position_errors, position_spread),
        ("orientation", orientation_errors, orientation_spread),
    ):
        errors = failed_as_infinite(errors)
        curves = ause(errors, spread)
        # Spearman ranks a missing spread with the largest, as the orderings above do.
        ranked_spread = np.where(np.isnan(spread), np.inf, spread)
        correlation = spearman(ranked_spread, errors)
        quality[kind] = {
            "spearman_spread_error": correlation,
            "spearman_uncertainty_error": correlation,
            "ause": curves["ause"],
            "failed_queries": curves["failed_queries"],
            "median_after_rejecting": rejection_medians(errors, spread),
            "sparsification": curves,
        }
    return quality
