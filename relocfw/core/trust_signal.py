"""What ranks an answer's trust, read the same way when bounds are calibrated and when
an answer is given its bounds (relocfw.core.error_bounds).

Higher is more trusted. A refined answer is ranked by the refiner's confidence (PnP
inliers, minus a retrieval distance) and is untrusted when it fell back to the
network's pose: its error is then the network's, a population of its own. A sampled
answer without a refiner (Bayesian PoseNet) is ranked by minus its spreads, position
and orientation each by their own. Anything else has no signal: one bound for all.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from relocfw.core.error_bounds import SIGNALS
from relocfw.core.values import Localization

if TYPE_CHECKING:
    from relocfw.core.error_bounds import ErrorBounds

CONFIDENCE, SPREAD, NONE = SIGNALS


def signal_name_of(answers: Sequence[Localization], refined: bool) -> str:
    """The signal a method's answers carry: the refiner's confidence where it has a
    refiner that gave any answer a finite one (refine=sequence gives none), else the
    spread where any answer was sampled, else none."""
    if refined and any(math.isfinite(a.refine_confidence) for a in answers):
        return CONFIDENCE
    if any(math.isfinite(a.position_spread) for a in answers):
        return SPREAD
    return NONE


def trust_of(answer: Localization, signal: str) -> tuple[float, float, bool]:
    """(position signal, orientation signal, untrusted) of one answer."""
    if signal == CONFIDENCE:
        confidence = float(answer.refine_confidence)
        return confidence, confidence, bool(answer.fell_back) or not math.isfinite(confidence)
    if signal == SPREAD:
        position, orientation = -answer.position_spread, -answer.orientation_spread_deg
        return position, orientation, not (math.isfinite(position) and math.isfinite(orientation))
    return math.nan, math.nan, False


def trust_arrays(
    answers: Sequence[Localization], signal: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`trust_of` for many answers: [N] position signals, orientation signals, untrusted."""
    found = [trust_of(a, signal) for a in answers]
    if not found:
        return np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool)
    position, orientation, untrusted = zip(*found, strict=True)
    return (
        np.array(position, dtype=np.float64),
        np.array(orientation, dtype=np.float64),
        np.array(untrusted, dtype=bool),
    )


def with_bounds(answer: Localization, bounds: ErrorBounds) -> Localization:
    """The answer with its calibrated position and orientation bounds."""
    position, orientation, untrusted = trust_of(answer, bounds.signal)
    return dataclasses.replace(
        answer,
        position_bound=float(bounds.position.bound(position, untrusted)),
        orientation_bound_deg=float(bounds.orientation.bound(orientation, untrusted)),
    )
