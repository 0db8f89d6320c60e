"""PoseNet's choice: the centre square, no search."""

from __future__ import annotations

from relocfw.core.interfaces import (
    CropProposals,
    CropSearch,
    SearchQuery,
    crop_at,
    crop_side_and_span,
)


class CentreCrop(CropSearch):
    """Always the middle square; the distance function is never called."""

    def propose(self, query: SearchQuery) -> CropProposals:
        _, span = crop_side_and_span(query.width, query.height)
        return crop_at(span // 2, query.width, query.height)
        yield  # a generator that asks for nothing: the pipeline scores the crop once
