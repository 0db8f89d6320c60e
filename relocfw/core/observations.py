"""What a reconstruction says one image sees: pixels of known 3-D points.

A COLMAP model (relocfw.data.colmap_points) records, per registered image, the 2-D
observations of its 3-D points: where in the image each track was measured. A
structure-based stage can then give its own keypoints those points instead of lifting
depth or triangulating again (relocfw.structure.colmap_structure).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relocfw.core.errors import DataError


@dataclass(frozen=True, eq=False)
class PointObservations:
    """The observed 3-D points of one image, row i for observation i.

    Attributes:
        keypoints: [N, 2] float64 pixel (x, y), measured from the centre of the
            top-left pixel (OpenCV's convention, as relocfw.core.camera; COLMAP's
            own values are half a pixel larger).
        points: [N, 3] float64 world points, in the units of the frames' poses.
        track_ids: [N] int64, the point's id in its reconstruction (COLMAP's
            POINT3D_ID): images that observe the same point share it.
        source: where they were read, for messages (not compared).

    Arrays are copied and made read-only. Equality is identity (eq=False), so a
    Frame holding observations can still be compared and hashed.

    Raises:
        DataError: naming `source` when the shapes disagree or a value is not finite.
    """

    keypoints: np.ndarray
    points: np.ndarray
    track_ids: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        where = self.source or "point observations"
        keypoints = np.array(self.keypoints, dtype=np.float64).reshape(-1, 2)
        points = np.array(self.points, dtype=np.float64)
        track_ids = np.array(self.track_ids, dtype=np.int64)
        count = len(keypoints)
        if points.shape != (count, 3) or track_ids.shape != (count,):
            raise DataError(
                f"{where}: {count} keypoints need [{count}, 3] points and [{count}] track "
                f"ids, got {list(points.shape)} and {list(track_ids.shape)}"
            )
        if not (np.isfinite(keypoints).all() and np.isfinite(points).all()):
            raise DataError(f"{where}: keypoints and points must be finite (found NaN or inf)")
        for name, array in (("keypoints", keypoints), ("points", points), ("track_ids", track_ids)):
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    def __len__(self) -> int:
        return len(self.keypoints)

    def __repr__(self) -> str:
        # A summary: the default would print every row.
        return f"PointObservations({len(self)} observations, source={self.source!r})"
