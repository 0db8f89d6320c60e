"""One frame of a stream to localize: what every frame source (image files, a video, a
ROS bag) yields, so `task=localize` reads them all the same way.

A module of its own so the sources can import it while `relocfw.data.streams`, which
dispatches to them, imports the sources: no import cycle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


# eq=False: frames hold pixel arrays, whose == is elementwise; identity is what counts.
@dataclass(frozen=True, eq=False)
class StreamFrame:
    """A frame and where it came from.

    Attributes:
        name: what localization.csv's image column shows: the file's path, or the
            frame's place in its stream.
        timestamp: as written to poses.txt: the frame's own time in seconds with 9
            decimals (video, bag), or for image files the file name's number when it
            is one, else the file's position in the list.
        image: H x W x 3 uint8 RGB pixels; None when the frame could not be decoded.
        error: why the frame could not be decoded (one line naming the frame); None
            when `image` is set.
    """

    name: str
    timestamp: str
    image: np.ndarray | None
    error: str | None = None
