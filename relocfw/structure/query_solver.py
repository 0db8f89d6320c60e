"""One query against the map's structure: features, matches to keyframes, the pose.

The query's RootSIFT features are extracted once and matched against the chosen map
images ("keyframes", e.g. the retrieved ones) in one call (one matrix product,
relocfw.structure.matching.match_against_views); every match whose map keypoint has
a 3-D point is a 2-D/3-D correspondence, and PoseLib's P3P LO-RANSAC solves the
camera-to-world pose from them (relocfw.structure.absolute_pose).

`keyframes_by_pose` chooses keyframes near a pose (a prior from the network, or
ground truth in a test).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import check_rgb_image
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.values import Pose
from relocfw.structure.absolute_pose import POSELIB_MIN_ITERATIONS, solve_absolute_pose
from relocfw.structure.covisibility import optical_axes
from relocfw.structure.features import LocalFeatures, checked_image_scale, extract_rootsift
from relocfw.structure.match_index import KnownMatches, MatchIndex
from relocfw.structure.matching import (
    checked_ratio,
    match_against_views,
    match_distances,
    one_match_per_query,
)
from relocfw.structure.query_checks import checked_keyframes
from relocfw.structure.structure_map import StructureMap, positions_of

TIMED_PARTS = ("features", "matching", "solve")


@dataclass(frozen=True)
class StructureAnswer:
    """What one query's solve against the structure gave.

    Attributes:
        pose: the camera-to-world Pose (metres, quaternion w first), None when the
            solve failed (the caller falls back to another pose and flags it).
        inliers: correspondences within the error bound of the pose found (0 when
            none was found).
        correspondences: 2-D/3-D correspondences the solver was given.
        success: True when a pose with at least `min_inliers` inliers was found.
        seconds: time per part, measured with time.perf_counter: "features"
            (extraction; 0.0 when the caller passed the features), "matching"
            (matching and gathering correspondences) and "solve".
        query_features: the query's LocalFeatures the solve used, so a second solve
            of the same query (against other keyframes) need not extract them again.
    """

    pose: Pose | None
    inliers: int
    correspondences: int
    success: bool
    seconds: dict[str, float] = field(default_factory=dict)
    query_features: LocalFeatures | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        # A copy, so the caller's dict cannot change a frozen answer afterwards.
        object.__setattr__(self, "seconds", dict(self.seconds))

    @property
    def total_seconds(self) -> float:
        """The sum of the timed parts."""
        return float(sum(self.seconds.values()))


def correspondences_of(
    structure: StructureMap, query: LocalFeatures, keyframes: Sequence[int], ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """The query's 2-D/3-D correspondences through its matches with the keyframes.

    Args:
        structure: the map.
        query: the query's LocalFeatures (N keypoints).
        keyframes: distinct map image indices (checked_keyframes), best first.
        ratio: Lowe's ratio in (0, 1].

    Returns:
        points_2d [K, 2] float64 query pixels and points_3d [K, 3] float64 world
        points, row i of each one correspondence, in query keypoint order. Each query
        keypoint gives at most one row: matched in several keyframes (to keypoints
        with a 3-D point), it keeps the match of the smallest descriptor distance, a
        tie going to the earlier keyframe (matching.one_match_per_query). Several
        rows of one keypoint would be one piece of evidence counted several times:
        they would pass min_inliers and raise the confidence without adding any.
    """
    views = [structure.features[i] for i in keyframes]
    matches = match_against_views(query, views, ratio)
    query_rows, world_rows, distances = [], [], []
    for slot, pairs in matches:
        points = structure.points[keyframes[slot]][pairs[:, 1]]
        has_point = np.isfinite(points).all(axis=1)
        query_rows.append(pairs[has_point, 0])
        world_rows.append(points[has_point])
        distances.append(match_distances(query, views[slot], pairs[has_point]))
    if not query_rows:
        return np.zeros((0, 2)), np.zeros((0, 3))
    indices = np.concatenate(query_rows)
    kept = one_match_per_query(indices, np.concatenate(distances))
    return (
        query.keypoints[indices[kept]].astype(np.float64),
        np.concatenate(world_rows)[kept].astype(np.float64),
    )


def localize_against(
    structure: StructureMap,
    query_image: np.ndarray | None,
    camera: PinholeCamera,
    keyframes: Sequence[int],
    max_features: int = 1024,
    ratio: float = 0.8,
    max_error_px: float = 8.0,
    min_inliers: int = 12,
    query_features: LocalFeatures | None = None,
    image_scale: float = 1.0,
    match_index: MatchIndex | None = None,
    min_iterations: int = POSELIB_MIN_ITERATIONS,
    known_matches: KnownMatches | None = None,
) -> StructureAnswer:
    """The pose of a query image from its matches with a few map images.

    Args:
        structure: the map (StructureMap).
        query_image: [H, W, 3] uint8 RGB of size camera.width x camera.height; may
            be None when `query_features` is given.
        camera: the query's intrinsics (undistorted pinhole).
        keyframes: indices of the map images to match against (e.g. retrieved);
            repeats are dropped; empty gives no correspondence.
        max_features: the most query keypoints (>= 1), when extracting.
        ratio: Lowe's ratio for the matches, in (0, 1].
        max_error_px: the inlier bound of the solve, in pixels (> 0).
        min_inliers: the fewest inliers a pose needs (>= 4).
        query_features: the query's LocalFeatures when the caller has them already
            (extracted at `camera`'s size); then `query_image` is not read and
            "features" takes 0 seconds.
        image_scale: the share of each side SIFT runs at, in (0, 1], when
            extracting (features.extract_rootsift; best the map's own).
        match_index: the map's MatchIndex (made once per map): matching then reads
            its stacked descriptors instead of stacking the keyframes' per query,
            and only the keypoints it holds (with a 3-D point, by default) are
            candidates. None: the keyframes' descriptors, every keypoint.
        min_iterations: the solve's fewest RANSAC rounds (absolute_pose).
        known_matches: with `match_index`, this query's matches per keyframe from
            an earlier solve of the same query features and ratio (filled here): a
            keyframe found there is not matched again. Not read without a match_index.

    Returns:
        StructureAnswer. Zero correspondences (a blank or unrelated image, keyframes
        without 3-D points) or a failed solve give success False and pose None;
        failing is an expected outcome, never an exception.

    Raises:
        DataError: when the image is not uint8 RGB of the camera's size, neither an
            image nor features are given, a keyframe is not an index of the map, or
            the query's descriptors are not the map's kind.
        ConfigError: naming `max_features`, `ratio`, `max_error_px` or
            `min_inliers` when out of range.
    """
    if not isinstance(structure, StructureMap):
        raise DataError(f"structure must be a StructureMap, got {type(structure).__name__}")
    if not isinstance(camera, PinholeCamera):
        raise DataError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    chosen = checked_keyframes(keyframes, len(structure))
    ratio = checked_ratio(ratio)  # before the extraction, so a wrong one fails at once
    max_features = integer_at_least("max_features", max_features, 1)
    min_inliers = integer_at_least("min_inliers", min_inliers, 4)
    bound = positive_number("max_error_px", max_error_px)
    image_scale = checked_image_scale(image_scale)
    if match_index is not None and len(match_index) != len(structure):
        raise DataError(
            f"match_index holds {len(match_index)} images, the structure {len(structure)}; "
            "make it with MatchIndex.of(structure)"
        )

    start = time.perf_counter()
    if query_features is None:
        if query_image is None:
            raise DataError("give query_image or query_features (both are None)")
        check_rgb_image(query_image, "query_image")
        height, width = query_image.shape[:2]
        if (width, height) != (camera.width, camera.height):
            raise DataError(
                f"query_image is {width}x{height} but the camera is "
                f"{camera.width}x{camera.height}; pass camera.scaled_to({width}, {height})"
            )
        query_features = extract_rootsift(query_image, max_features, image_scale)
    elif not isinstance(query_features, LocalFeatures):
        raise DataError(
            f"query_features must be LocalFeatures, got {type(query_features).__name__}"
        )
    features_done = time.perf_counter()
    if match_index is None:
        points_2d, points_3d = correspondences_of(structure, query_features, chosen, ratio)
    else:
        points_2d, points_3d = match_index.correspondences(
            query_features, chosen, ratio, known_matches
        )
    matching_done = time.perf_counter()
    solved = solve_absolute_pose(points_2d, points_3d, camera, bound, min_inliers, min_iterations)
    solve_done = time.perf_counter()
    return StructureAnswer(
        pose=solved.pose,
        inliers=solved.inliers,
        correspondences=len(points_2d),
        success=solved.success,
        query_features=query_features,
        seconds={
            "features": features_done - start,
            "matching": matching_done - features_done,
            "solve": solve_done - matching_done,
        },
    )


@dataclass(frozen=True, eq=False)
class MapViewpoints:
    """Where each map image stands and which way it looks, computed once per map, so
    that choosing keyframes by pose is two array operations a query, not the axes of
    every map pose again (400 Red Kitchen map poses: 1 ms a query from the poses,
    0.06 ms from their viewpoints; 12 ms while each pose's axis was a scipy call).

    Attributes:
        positions: [M, 3] camera positions in the world.
        axes: [M, 3] unit viewing directions (camera z axes) in the world.
    """

    positions: np.ndarray
    axes: np.ndarray

    @classmethod
    def of(cls, structure_or_poses: StructureMap | Sequence[Pose]) -> MapViewpoints:
        """The viewpoints of a map or of its camera-to-world poses; DataError when
        they are not Poses."""
        poses = (
            structure_or_poses.poses
            if isinstance(structure_or_poses, StructureMap)
            else list(structure_or_poses)
        )
        if not all(isinstance(p, Pose) for p in poses):
            raise DataError("structure_or_poses must be a StructureMap or a sequence of Poses")
        return cls(positions_of(poses), optical_axes(poses))

    def __len__(self) -> int:
        return len(self.positions)


def keyframes_by_pose(
    structure_or_poses: StructureMap | Sequence[Pose] | MapViewpoints,
    pose: Pose,
    count: int,
    max_angle_deg: float = 45.0,
) -> list[int]:
    """The map images nearest to a pose in position among those looking its way.

    Args:
        structure_or_poses: the map, its M camera-to-world poses, or their
            MapViewpoints (computed once, for many queries).
        pose: the camera-to-world pose to choose for (a prior).
        count: how many images at most (>= 1).
        max_angle_deg: the largest angle between the pose's optical axis and a map
            image's, in degrees, in [0, 180].

    Returns:
        Up to `count` indices, nearest first (ties by index): of the images within
        `max_angle_deg`; when none is, of all images (a prior that looks nowhere
        the map looked still gets its nearest images). Fewer than `count` when fewer
        images qualify.

    Raises:
        ConfigError: naming `count` or `max_angle_deg` when out of range.
        DataError: when `pose` is not a finite Pose or the poses are not Poses.
    """
    count = integer_at_least("count", count, 1)
    try:
        angle = float(max_angle_deg)
    except (TypeError, ValueError):
        angle = math.nan
    if not 0.0 <= angle <= 180.0:
        raise ConfigError(f"max_angle_deg must be in [0, 180] degrees, got {max_angle_deg!r}")
    if not isinstance(pose, Pose):
        raise DataError(f"pose must be a Pose, got {type(pose).__name__}")
    if not pose.is_finite:
        # NaN distances would all sort last and pick images 0..count-1 as if chosen.
        raise DataError("pose holds NaN or infinity: no map image is near it")
    viewpoints = (
        structure_or_poses
        if isinstance(structure_or_poses, MapViewpoints)
        else MapViewpoints.of(structure_or_poses)
    )
    if not len(viewpoints):
        return []
    distances = np.linalg.norm(viewpoints.positions - pose.position, axis=1)
    axis = optical_axes([pose])[0]
    # The cosine bound with a little slack, so an image at exactly the bound counts.
    facing = viewpoints.axes @ axis >= math.cos(math.radians(angle)) - 1e-12
    candidates = np.flatnonzero(facing) if facing.any() else np.arange(len(viewpoints))
    order = np.argsort(distances[candidates], kind="stable")[:count]
    return candidates[order].tolist()
