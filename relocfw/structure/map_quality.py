"""How good an RGB-only map is: how many keypoints got a 3-D point, and how far those
points lie from where the map images' depth maps put the same keypoints.

Depth is read as build_from_depth reads it (depth_structure.depth_of_view): a view
with a depth camera (7-Scenes: the 585 sensor and the Kinect's depth-to-colour
transform) has its depth registered into the colour image first
(relocfw.structure.registration), so each keypoint is compared with the depth of its
own surface point; a view without one is read pixel for pixel as registered already.
Registration leaves holes where the depth sensor did not see, and the sensor's own
noise, larger near depth edges and with distance, stays in the reference.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from relocfw.core.errors import DataError
from relocfw.structure.depth_structure import depth_of_view
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.map_view import MapView
from relocfw.structure.structure_map import StructureMap


@dataclass(frozen=True)
class DepthAgreement:
    """Triangulated points against depth-lifted points of the same keypoints.

    Attributes:
        compared: keypoints with both a triangulated point and a depth reading.
        median_error_m: median 3-D distance between the two points.
        within_5cm: share of the compared points within 5 cm.
        median_range_ratio: median of (camera-to-point distance triangulated) /
            (the same from depth): 1 when the map's scale agrees with the depth's (a
            wrong focal length shows here: 585 / 525 = 1.11).
    """

    compared: int
    median_error_m: float
    within_5cm: float
    median_range_ratio: float


def point_share(structure: StructureMap) -> float:
    """The share of the map's keypoints that have a 3-D point (0.0 for no keypoint)."""
    total = sum(len(f) for f in structure.features)
    return float(structure.point_counts().sum()) / total if total else 0.0


def depth_agreement(structure: StructureMap, views: Sequence[MapView]) -> DepthAgreement:
    """How far the map's points lie from the depth maps' points of the same keypoints.

    Args:
        structure: a map built from `views` (image i of each is the same image).
        views: the map views with their depth paths; views without usable depth
            are left out.

    Raises:
        DataError: when `views` and the map differ in count or names.
    """
    if len(views) != len(structure) or [v.name for v in views] != list(structure.names):
        raise DataError("views must be the map's own images, in the map's order")
    errors, ratios = [], []
    for view, features, points, pose in zip(
        views, structure.features, structure.points, structure.poses, strict=True
    ):
        depth, _ = depth_of_view(view)
        if depth is None or len(features) == 0:
            continue
        lifted = lift_keypoints(features.keypoints, depth, view.camera, pose)
        both = np.isfinite(points).all(axis=1) & np.isfinite(lifted).all(axis=1)
        if not both.any():
            continue
        errors.append(np.linalg.norm(points[both] - lifted[both], axis=1))
        centre = np.asarray(pose.position, dtype=np.float64)
        ratios.append(
            np.linalg.norm(points[both] - centre, axis=1)
            / np.linalg.norm(lifted[both] - centre, axis=1)
        )
    if not errors:
        return DepthAgreement(0, float("nan"), float("nan"), float("nan"))
    distance = np.concatenate(errors)
    return DepthAgreement(
        compared=int(len(distance)),
        median_error_m=float(np.median(distance)),
        within_5cm=float(np.mean(distance <= 0.05)),
        median_range_ratio=float(np.median(np.concatenate(ratios))),
    )
