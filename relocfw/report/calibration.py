"""Calibrating a fitted pipeline's error bounds on a validation block, and measuring
how often the bounds hold on a test split.

Split conformal prediction (relocfw.core.error_bounds): the method answers validation
frames that neither its network nor its map has seen, and the errors it makes there,
binned by its trust signal (relocfw.core.trust_signal), bound the errors of later
answers. The guarantee holds for queries like the validation block's; queries farther
from the map than the block are not covered by it, which is why coverage is measured
on the test splits rather than assumed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from relocfw.core.error_bounds import ErrorBounds, calibrate
from relocfw.core.pipeline import Relocalizer
from relocfw.core.trust_signal import signal_name_of, trust_arrays
from relocfw.data.frames import Frame
from relocfw.report.evaluation import MethodResult, evaluate


@dataclass(frozen=True)
class Calibration:
    """What `calibrate_relocalizer` needs: the held-out frames and images (the last
    `calibrate.share` of the training split), the coverage and the most bins."""

    frames: Sequence[Frame]
    images: Sequence[np.ndarray]
    coverage: float = 0.9
    bins: int = 3


def calibrate_relocalizer(
    relocalizer: Relocalizer, calibration: Calibration, quiet: bool = False
) -> tuple[ErrorBounds, MethodResult]:
    """Answer the validation frames with the fitted pipeline, set its `bounds` from
    their errors and return them with the validation answers.

    The pipeline answers without bounds while calibrating, and its refiner forgets the
    validation frames afterwards (a tracking refiner must not carry the block's last
    pose into the test split).
    """
    relocalizer.bounds = None
    result = evaluate(
        "calibration", relocalizer, calibration.frames, calibration.images, quiet=quiet
    )
    if relocalizer.refiner is not None:
        relocalizer.refiner.reset()
    bounds = bounds_of(result, relocalizer.refiner is not None, calibration)
    relocalizer.bounds = bounds
    return bounds, result


def bounds_of(result: MethodResult, refined: bool, calibration: Calibration) -> ErrorBounds:
    """The error bounds of a method's validation answers."""
    signal = signal_name_of(result.answers, refined)
    position, orientation, untrusted = trust_arrays(result.answers, signal)
    options = {"coverage": calibration.coverage, "bins": calibration.bins}
    return ErrorBounds(
        coverage=calibration.coverage,
        signal=signal,
        position=calibrate(result.position_errors(), position, untrusted, **options),
        orientation=calibrate(result.orientation_errors(), orientation, untrusted, **options),
        validation_size=len(result.answers),
    )
