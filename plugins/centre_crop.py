"""PoseNet's choice: the centre square, no search."""

from __future__ import annotations

from relocfw.core.interfaces import CropDistance, CropSearch, crop_at, crop_side_and_span
from relocfw.core.values import Crop


class CentreCrop(CropSearch):
    """Always the middle square; the distance function is never called."""

    def search(self, width: int, height: int, distance: CropDistance) -> Crop:
        _, span = crop_side_and_span(width, height)
        return crop_at(span // 2, width, height)
