"""Descriptors of many crop windows from one pass of the trunk over the whole strip.

Every candidate crop of a query is a window of the same strip (relocfw.core.imaging.Strip),
and a PoseNet-style descriptor is a layer on the global average of the trunk's last
maps. Run the trunk once on the strip: each map column (row, for a portrait image)
then summarises one band of the strip, and a window's pooled input is the average of
the cells it covers, with fractional weights for the cells at its two ends. The trunk,
nearly all of the network's work, runs once per query instead of once per candidate;
each further candidate costs one weighted sum and the descriptor layer.

This is an approximation, not an identity: on the strip, cells near a window's edge
see the image beyond the edge where the plain path sees zero padding. So the pipeline
uses it only to rank candidates (scoring=shared) and puts the chosen crop through the
plain path once: the pose it answers with is exactly the plain path's pose for that
crop. `benchmarks/query_cost.py` reports how far shared descriptors are from plain ones.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch


def coverage_weights(starts: torch.Tensor, length: int, cells: int) -> torch.Tensor:
    """[n, cells]: the share of interval [start, start + length) lying in cell [j, j+1).

    Each row sums to 1 when the interval lies inside [0, cells).
    """
    edges = torch.arange(cells, dtype=starts.dtype, device=starts.device)
    low = torch.maximum(starts[:, None], edges)
    high = torch.minimum(starts[:, None] + length, edges + 1)
    return (high - low).clamp(min=0) / length


class StripMaps:
    """The trunk's maps of one strip, ready to pool any window of it.

    Args:
        maps: [C, h, w] last convolutional maps of the whole strip.
        strip_height: strip height in pixels.
        strip_width: strip width in pixels.
        input_size: the window side in pixels (the network input).
        window_cells: how many cells a window spans along each axis. None: all cells
            of the short axis, as when the window is the strip's whole short side
            (crop_scale 1); with crop_scale > 1 the caller measures it (the maps of
            one input-sized image).
    """

    def __init__(
        self,
        maps: torch.Tensor,
        strip_height: int,
        strip_width: int,
        input_size: int,
        window_cells: int | None = None,
    ) -> None:
        self.maps = maps
        cells_y, cells_x = maps.shape[1:]
        if window_cells is None:
            window_cells = cells_y if strip_width >= strip_height else cells_x
        self.window_cells = window_cells
        # Offset 0 starts at cell 0 and the far edge ends at the last cell; the maps'
        # rounded sizes make a plain pixels / stride mapping overrun by a fraction.
        self.cells_per_pixel = tuple(
            (cells - window_cells) / (length - input_size) if length > input_size else 0.0
            for cells, length in ((cells_y, strip_height), (cells_x, strip_width))
        )

    def pooled(self, corners: Sequence[tuple[int, int]]) -> torch.Tensor:
        """[n, C] approximate global-average-pooled maps of the windows at `corners`."""
        weights = []
        for axis in (0, 1):
            starts = torch.tensor(
                [corner[axis] for corner in corners], dtype=self.maps.dtype, device=self.maps.device
            )
            cells = self.maps.shape[1 + axis]
            weights.append(
                coverage_weights(starts * self.cells_per_pixel[axis], self.window_cells, cells)
            )
        # Separable: a window's weight on cell (i, j) is its row share times its column share.
        return torch.einsum("ni,cij,nj->nc", weights[0], self.maps, weights[1])
