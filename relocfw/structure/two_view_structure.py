"""A structure map from RGB map images of known pose by two-view triangulation: the
builder before multi-view tracks, kept for side-by-side rows
(`refine.triangulation.method=two_view`)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np

from relocfw.core.errors import ConfigError
from relocfw.core.options import integer_at_least
from relocfw.core.progress import Progress
from relocfw.core.values import Pose
from relocfw.structure.covisibility import optical_axes
from relocfw.structure.map_view import MapView
from relocfw.structure.matching import checked_ratio, match_against_views
from relocfw.structure.structure_map import SkippedView, StructureMap, positions_of
from relocfw.structure.triangulation import checked_bound, triangulate
from relocfw.structure.view_features import checked_views, features_of_views


def triangulation_partners(
    poses: Sequence[Pose],
    partners: int = 3,
    max_distance_m: float | None = None,
    min_baseline_m: float = 0.05,
    max_axis_angle_deg: float = 30.0,
) -> list[list[int]]:
    """For each map image, the other map images to triangulate its keypoints with.

    A partner looks a similar way (the angle between the two optical axes is at most
    `max_axis_angle_deg`, so the two images share much of their view and their
    features still match), is at least `min_baseline_m` away (a short baseline fixes
    no depth) and at most `max_distance_m`; of those, the nearest `partners` in
    position (ties by index).

    Args:
        poses: M camera-to-world poses.
        partners: how many partners per image, at most (>= 1).
        max_distance_m: the farthest a partner may be, or None for no bound.
        min_baseline_m: the nearest a partner may be (>= 0).
        max_axis_angle_deg: the largest angle between optical axes, in [0, 180).

    Returns:
        M lists of indices, each sorted nearest first; empty where no image
        qualifies.

    Raises:
        ConfigError: naming the argument out of range.
    """
    partners = integer_at_least("partners", partners, 1)
    min_baseline = checked_bound("min_baseline_m", min_baseline_m, 0.0, math.inf)
    max_angle = checked_bound("max_axis_angle_deg", max_axis_angle_deg, 0.0, 180.0)
    max_distance = (
        math.inf
        if max_distance_m is None
        else checked_bound("max_partner_distance_m", max_distance_m, 0.0, math.inf)
    )
    positions = positions_of(poses)
    axes = optical_axes(poses)
    cosine_bound = math.cos(math.radians(max_angle))
    chosen = []
    # One row at a time: O(M) memory, where an M x M distance matrix of a map of
    # 20,000 images would take 3 GB.
    for i in range(len(positions)):
        distances = np.linalg.norm(positions - positions[i], axis=1)
        eligible = (
            (axes @ axes[i] >= cosine_bound)
            & (distances >= min_baseline)
            & (distances <= max_distance)
        )
        eligible[i] = False
        candidates = np.flatnonzero(eligible)
        order = np.argsort(distances[candidates], kind="stable")[:partners]
        chosen.append(candidates[order].tolist())
    return chosen


def median_camera_spacing(poses: Sequence[Pose]) -> float:
    """The median distance from a map image's camera to its nearest other camera: the
    map's own length scale, for a map whose unit is not the metre.

    Args:
        poses: M camera-to-world poses.

    Returns:
        The median over images of the distance to the nearest other position (0.0
        when fewer than two images, or all stand in one place).
    """
    positions = positions_of(poses)
    if len(positions) < 2:
        return 0.0
    nearest = np.empty(len(positions))
    # One row at a time, as triangulation_partners: O(M) memory.
    for i in range(len(positions)):
        distances = np.linalg.norm(positions - positions[i], axis=1)
        distances[i] = np.inf
        nearest[i] = distances.min()
    return float(np.median(nearest))


def median_of_candidates(candidates: np.ndarray) -> np.ndarray:
    """Per keypoint, the component-wise median of its valid triangulations.

    Args:
        candidates: [N, P, 3] points, NaN rows where a partner gave none.

    Returns:
        [N, 3] float32; NaN rows where no partner gave a point.
    """
    with warnings.catch_warnings():
        # An all-NaN keypoint (no valid triangulation) is expected: it stays NaN.
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(candidates, axis=1).astype(np.float32)


def build_by_two_view_triangulation(
    views: Sequence[MapView],
    max_features: int = 1024,
    partners: int = 3,
    max_partner_distance_m: float | None = None,
    min_baseline_m: float = 0.05,
    max_axis_angle_deg: float = 30.0,
    min_angle_deg: float = 2.0,
    max_reprojection_px: float = 4.0,
    ratio: float = 0.8,
    quiet: bool = False,
    image_scale: float = 1.0,
) -> StructureMap:
    """The structure of RGB map images of known pose, by two-view triangulation (the
    builder before multi-view tracks; `build_by_triangulation(method="two_view")`).

    For each map image i: its partners (`triangulation_partners`: similar viewing
    direction, baseline between `min_baseline_m` and `max_partner_distance_m`, the
    nearest `partners`) are matched against it in one call (mutual nearest
    neighbours with Lowe's ratio test); each match is triangulated with the two
    known poses (relocfw.structure.triangulation.triangulate: in front of both
    cameras, within `max_reprojection_px` of both keypoints, rays meeting at
    `min_angle_deg` or more), and keypoint k of image i gets the component-wise
    MEDIAN of its valid triangulations. Why the median and not the smallest
    reprojection error: the reprojection error of a two-view point says little
    about its depth (at a narrow ray angle a point far off along the rays still
    reprojects perfectly, so the smallest error favours the worst-conditioned
    pair), while the median rejects one wrong match (one that happens to lie near
    its epipolar line) among three partners and averages the others' noise.

    Each view is read once, in order (its features are extracted, then only
    features and poses are used), so `views` may be a lazy sequence.

    Args:
        views: the map images (M), each with pose and camera (depth is not read).
        max_features: the most keypoints per image (>= 1).
        partners: the most partner images per image (>= 1).
        max_partner_distance_m: the farthest a partner may be, None for no bound.
        min_baseline_m: the nearest a partner may be (>= 0).
        max_axis_angle_deg: the largest angle between the optical axes of an image
            and a partner, in degrees.
        min_angle_deg: the smallest angle between the two rays of a triangulated
            point, in degrees (at 2 degrees, 0.5 px of noise at f = 585 px moves a
            point 2 m away by about 3 cm along the ray).
        max_reprojection_px: the largest reprojection error of a triangulated point
            in either image, in pixels.
        ratio: Lowe's ratio for the matches, in (0, 1].
        quiet: show no progress bar.
        image_scale: the share of each side SIFT runs at, in (0, 1].

    Returns:
        StructureMap with source "triangulated"; `skipped_views` lists images with
        no valid point (no partner within the limits, or no match triangulated).

    Raises:
        DataError: naming the view when an entry is not a MapView or its pose is not
            finite.
        ConfigError: naming the argument out of range.
    """
    checked_views(views)
    max_features = integer_at_least("max_features", max_features, 1)
    ratio = checked_ratio(ratio)
    # Checked before the slow part, so a wrong argument fails at once.
    checked_bound("min_angle_deg", min_angle_deg, 0.0, 180.0)
    if checked_bound("max_reprojection_px", max_reprojection_px, 0.0, math.inf) <= 0:
        raise ConfigError(f"max_reprojection_px must be above 0, got {max_reprojection_px!r}")
    count = len(views)
    progress = Progress(2 * count, "map structure by triangulation", quiet=quiet)
    features, poses, cameras, names = features_of_views(views, max_features, progress, image_scale)
    chosen = triangulation_partners(
        poses, partners, max_partner_distance_m, min_baseline_m, max_axis_angle_deg
    )
    points, skipped = [], []
    for i in range(count):
        own = features[i]
        candidates = np.full((len(own), max(1, len(chosen[i])), 3), np.nan)
        matches = match_against_views(own, [features[j] for j in chosen[i]], ratio)
        for slot, pairs in matches:
            j = chosen[i][slot]
            triangulated, valid = triangulate(
                own.keypoints[pairs[:, 0]],
                features[j].keypoints[pairs[:, 1]],
                cameras[i],
                poses[i],
                cameras[j],
                poses[j],
                max_reprojection_px=max_reprojection_px,
                min_angle_deg=min_angle_deg,
            )
            # Mutual matching pairs each keypoint of i with at most one of j's, so
            # no slot is written twice.
            candidates[pairs[valid, 0], slot] = triangulated[valid]
        best = median_of_candidates(candidates)
        if not chosen[i]:
            skipped.append(SkippedView(names[i], "no partner view within the limits"))
        elif not np.isfinite(best).all(axis=1).any():
            skipped.append(
                SkippedView(names[i], f"no match triangulated with {len(chosen[i])} partner(s)")
            )
        points.append(best)
        progress.advance(suffix="triangulation")
    progress.close()
    return StructureMap(
        features=tuple(features),
        points=tuple(points),
        poses=tuple(poses),
        cameras=tuple(cameras),
        names=tuple(names),
        source="triangulated",
        skipped_views=tuple(skipped),
    )
