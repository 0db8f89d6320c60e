"""How well a sampled method's spread tells good answers from bad ones.

Bayesian PoseNet and test-time sampling give each answer a spread (position spread in
metres, orientation spread in degrees). A useful uncertainty ranks queries by their
error. Measured here the way the literature does:

- the Spearman rank correlation of spread with error;
- the sparsification curve: the median error of the queries kept as the most
  uncertain fraction is removed, against the same curve when queries are removed by
  their true error (the oracle); AUSE, the area between the two (0: the spread ranks
  queries exactly as their errors do);
- the median error left after rejecting the 10 / 20 / 30 % most uncertain queries.
"""

from __future__ import annotations

import numpy as np

from relocfw.report.statistics import spearman

REJECTION_SHARES = (0.1, 0.2, 0.3)


def sparsification_curve(errors: np.ndarray, order: np.ndarray) -> np.ndarray:
    """[N] median error of the queries kept after removing the first i of `order`.

    Entry i removes the i queries that come first in `order` (most uncertain first),
    so entry 0 is the median over all queries and entry N-1 keeps one query.
    """
    errors = np.asarray(errors, dtype=np.float64)
    kept_last_first = errors[np.asarray(order)][::-1]
    # The median of each suffix of `order`, computed once per length.
    return np.array([np.median(kept_last_first[: len(errors) - i]) for i in range(len(errors))])


def most_uncertain_first(uncertainty: np.ndarray) -> np.ndarray:
    """Query indices from the largest spread to the smallest (stable among ties)."""
    return np.argsort(-np.asarray(uncertainty, dtype=np.float64), kind="stable")


def ause(errors: np.ndarray, uncertainty: np.ndarray) -> dict[str, object]:
    """Sparsification curves and the area between them.

    Returns:
        `fractions` removed (i / N), `by_uncertainty` and `oracle` curves, and `ause`,
        the mean over fractions of (by_uncertainty - oracle): the area between the
        curves on [0, 1), in the errors' unit. 0 when the spread orders the queries as
        their errors do; largest when it orders them in reverse.
    """
    errors = np.asarray(errors, dtype=np.float64)
    by_uncertainty = sparsification_curve(errors, most_uncertain_first(uncertainty))
    oracle = sparsification_curve(errors, most_uncertain_first(errors))
    gap = by_uncertainty - oracle
    # inf - inf where both keep a failed query in the median: no gap there.
    gap = np.where(np.isnan(gap), 0.0, gap)
    return {
        "fractions": (np.arange(len(errors)) / len(errors)).tolist(),
        "by_uncertainty": by_uncertainty.tolist(),
        "oracle": oracle.tolist(),
        "ause": float(np.mean(gap)),
    }


def rejection_medians(
    errors: np.ndarray, uncertainty: np.ndarray, shares: tuple[float, ...] = REJECTION_SHARES
) -> dict[str, float]:
    """Median error after rejecting each share of the most uncertain queries."""
    errors = np.asarray(errors, dtype=np.float64)
    order = most_uncertain_first(uncertainty)
    out = {}
    for share in shares:
        rejected = int(round(share * len(errors)))
        kept = order[rejected:] if rejected < len(errors) else order[-1:]
        out[f"{share:.0%}"] = float(np.median(errors[kept]))
    return out


def uncertainty_quality(
    position_errors: np.ndarray,
    orientation_errors: np.ndarray,
    position_spread: np.ndarray,
    orientation_spread: np.ndarray,
) -> dict[str, object] | None:
    """Every measure above for position and orientation; None when nothing was sampled."""
    position_spread = np.asarray(position_spread, dtype=np.float64)
    orientation_spread = np.asarray(orientation_spread, dtype=np.float64)
    if np.all(np.isnan(position_spread)):
        return None
    quality: dict[str, object] = {}
    for kind, errors, spread in (
        ("position", position_errors, position_spread),
        ("orientation", orientation_errors, orientation_spread),
    ):
        # A query without a spread is treated as the most uncertain (it is not dropped).
        spread = np.where(np.isnan(spread), np.inf, spread)
        curves = ause(errors, spread)
        quality[kind] = {
            "spearman_spread_error": spearman(spread, errors),
            "ause": curves["ause"],
            "median_after_rejecting": rejection_medians(errors, spread),
            "sparsification": curves,
        }
    return quality
