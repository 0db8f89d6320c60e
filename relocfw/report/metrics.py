"""The field's accuracy metrics over one method's per-query errors.

A query without a finite pose has failed. It counts as infinitely wrong: it lowers
every share and raises the median, and is never dropped (dropping failures is how a
method that gives up on hard queries would look better than one that answers them).
"""

from __future__ import annotations

import numpy as np

# (metres, degrees): the usual recall bands of the relocalization literature. 5 cm /
# 5 deg is the 7-Scenes convention of scene coordinate regression (Shotton et al.
# 2013, DSAC); the last three are the fine / medium / coarse bands of the long-term
# visual localization benchmark (Sattler et al. 2018) that hloc reports. Both limits
# are strict (error < limit), as in hloc's evaluation; test_metrics.py pins it.
RECALL_BANDS: tuple[tuple[float, float], ...] = ((0.05, 5.0), (0.25, 2.0), (0.5, 5.0), (5.0, 10.0))

# The paper's Figure 7 shares: below 0.5 m, below 15 deg, above 1 m, above 20 deg.
POSITION_WITHIN_M = 0.5
ORIENTATION_WITHIN_DEG = 15.0
POSITION_BEYOND_M = 1.0
ORIENTATION_BEYOND_DEG = 20.0


def failed_as_infinite(errors: np.ndarray) -> np.ndarray:
    """Errors with every non-finite entry (a failed query) set to +inf."""
    errors = np.asarray(errors, dtype=np.float64)
    return np.where(np.isfinite(errors), errors, np.inf)


def band_key(metres: float, degrees: float) -> str:
    """Summary key of a recall band, e.g. `within_0.25m_2deg`."""
    return f"within_{metres:g}m_{degrees:g}deg"


def band_title(metres: float, degrees: float) -> str:
    """Table title of a recall band, e.g. `25cm/2deg`."""
    distance = f"{metres * 100:g}cm" if metres < 1 else f"{metres:g}m"
    return f"{distance}/{degrees:g}deg"


def accuracy_metrics(positions: np.ndarray, orientations: np.ndarray) -> dict[str, float | int]:
    """Medians, means, recall bands and the paper's shares of one method's errors.

    Args:
        positions: [N] position errors in metres; NaN or inf where the query failed.
        orientations: [N] orientation errors in degrees; NaN or inf where it failed.

    Returns:
        A flat dict: `failed_queries`; median and mean position (m) and orientation
        (deg); `within_{m}m_{deg}deg` for each RECALL_BANDS entry (both below, strictly);
        the paper's shares `share_position_below_0.5m`, `share_orientation_below_15deg`,
        `share_position_above_1m`, `share_orientation_above_20deg`, and the joint
        `share_within_0.5m_15deg`.
    """
    positions = failed_as_infinite(positions)
    orientations = failed_as_infinite(orientations)
    if positions.shape != orientations.shape or positions.ndim != 1 or not len(positions):
        raise ValueError(f"need two equal, non-empty [N] arrays, got {positions.shape}")
    failed = ~(np.isfinite(positions) & np.isfinite(orientations))
    # A query whose position is finite but orientation is not (or the reverse) failed.
    positions = np.where(failed, np.inf, positions)
    orientations = np.where(failed, np.inf, orientations)
    metrics: dict[str, float | int] = {
        "failed_queries": int(failed.sum()),
        "median_position_m": float(np.median(positions)),
        "mean_position_m": float(np.mean(positions)),
        "median_orientation_deg": float(np.median(orientations)),
        "mean_orientation_deg": float(np.mean(orientations)),
    }
    for metres, degrees in RECALL_BANDS:
        within = (positions < metres) & (orientations < degrees)
        metrics[band_key(metres, degrees)] = float(np.mean(within))
    metrics["share_position_below_0.5m"] = float(np.mean(positions < POSITION_WITHIN_M))
    metrics["share_orientation_below_15deg"] = float(np.mean(orientations < ORIENTATION_WITHIN_DEG))
    metrics["share_position_above_1m"] = float(np.mean(positions > POSITION_BEYOND_M))
    metrics["share_orientation_above_20deg"] = float(np.mean(orientations > ORIENTATION_BEYOND_DEG))
    metrics["share_within_0.5m_15deg"] = float(
        np.mean((positions < POSITION_WITHIN_M) & (orientations < ORIENTATION_WITHIN_DEG))
    )
    return metrics
