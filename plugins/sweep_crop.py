"""Exhaustive sweep: score every crop offset (or every stride-th) and keep the best."""

from __future__ import annotations

import numpy as np

from relocfw.core.interfaces import (
    CropProposals,
    CropSearch,
    SearchQuery,
    crop_at,
    crop_side_and_span,
)
from relocfw.core.options import integer_at_least


class SweepCrop(CropSearch):
    """The exact minimum over a grid of offsets; the upper bound for any search.

    Args:
        stride: pixels between tried offsets; 1 tries every offset. The last offset
            (the far edge) is always tried.
    """

    def __init__(self, stride: int = 1) -> None:
        self.stride = integer_at_least("stride", stride, 1)

    def propose(self, query: SearchQuery) -> CropProposals:
        _, span = crop_side_and_span(query.width, query.height)
        offsets = list(range(0, span + 1, self.stride))
        if offsets[-1] != span:
            offsets.append(span)
        crops = [crop_at(o, query.width, query.height) for o in offsets]
        distances = yield crops  # every offset in one batch
        return crops[int(np.argmin(distances))]
