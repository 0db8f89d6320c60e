"""The map's structure from a COLMAP model's own 3-D points (refine.structure=colmap).

A COLMAP model already holds what the other two builders make: tracks of features
across the map images, triangulated over all their views and bundle adjusted. Its
features are COLMAP's, though, and a query is matched with relocfw's RootSIFT
(relocfw.structure.features), so each map image's own keypoints are extracted as
usual and each takes the 3-D point of the COLMAP observation it sits on: the nearest
within `radius_px`, one to one. Both detectors are SIFT's difference of Gaussians on
the same pixels, so most of the model's observations have a keypoint within a pixel
or two. Every keyframe that observed a COLMAP point gets that point's one position,
so matching and PnP run unchanged on the result.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.observations import PointObservations
from relocfw.core.options import integer_at_least
from relocfw.core.progress import Progress
from relocfw.structure.features import checked_image_scale, extract_rootsift
from relocfw.structure.map_view import MapView
from relocfw.structure.structure_map import SkippedView, StructureMap, on_descriptor_grid
from relocfw.structure.view_features import checked_view, checked_views

# Keypoints compared with every observation at once, at most: a map image of 20,000
# observations then needs about 20 MB for its distances, not one row per keypoint.
DISTANCE_ROWS = 256


def nearest_observations(
    keypoints: np.ndarray, observed: np.ndarray, radius_px: float
) -> np.ndarray:
    """For each keypoint, the observation it takes: the nearest one within `radius_px`,
    one to one, greedily by distance (the closest pair of all first).

    Args:
        keypoints: [N, 2] pixels (x, y).
        observed: [K, 2] pixels of the observations, in the same convention.
        radius_px: the farthest an observation may be from its keypoint.

    Returns:
        [N] int64 rows of `observed`; -1 where a keypoint takes none.
    """
    keypoints = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    observed = np.asarray(observed, dtype=np.float64).reshape(-1, 2)
    chosen = np.full(len(keypoints), -1, dtype=np.int64)
    if not len(keypoints) or not len(observed):
        return chosen
    rows, columns, distances = [], [], []
    for start in range(0, len(keypoints), DISTANCE_ROWS):
        block = keypoints[start : start + DISTANCE_ROWS]
        squared = ((block[:, None, :] - observed[None, :, :]) ** 2).sum(axis=2)
        near_rows, near_columns = np.nonzero(squared <= radius_px**2)
        rows.append(near_rows + start)
        columns.append(near_columns)
        distances.append(squared[near_rows, near_columns])
    row, column, distance = (np.concatenate(parts) for parts in (rows, columns, distances))
    # Greedy by distance: a pair is kept when neither side is taken yet. Candidates
    # within a few pixels are about as many as keypoints, so the loop is short.
    taken = np.zeros(len(observed), dtype=bool)
    for index in np.lexsort((column, row, distance)).tolist():
        if chosen[row[index]] < 0 and not taken[column[index]]:
            chosen[row[index]] = column[index]
            taken[column[index]] = True
    return chosen


def checked_radius(radius_px: float) -> float:
    """`radius_px` as a float when it is a positive finite number, else a ConfigError."""
    number = isinstance(radius_px, int | float) and not isinstance(radius_px, bool)
    if not (number and math.isfinite(radius_px) and radius_px > 0):
        raise ConfigError(f"refine.radius_px must be a positive number, got {radius_px!r}")
    return float(radius_px)


def build_from_colmap_points(
    views: Sequence[MapView],
    observations: Sequence[PointObservations | None],
    max_features: int = 1024,
    radius_px: float = 2.5,
    quiet: bool = False,
    image_scale: float = 1.0,
) -> StructureMap:
    """The structure of map images whose 3-D points a COLMAP model holds.

    Each view's RootSIFT keypoints (extract_rootsift) take the 3-D points of its
    observations (nearest_observations: within `radius_px`, one to one); the other
    keypoints keep NaN rows and still take part in matching, as in the other maps.

    Args:
        views: the map images (M), each with pose and camera (depth is not read).
        observations: per view, the model's observations in the view's pixels
            (relocfw.data.colmap_points), None where the model has none.
        max_features: the most keypoints per image (>= 1).
        radius_px: the farthest an observation may be from the keypoint taking it.
        quiet: show no progress bar.
        image_scale: the share of each side SIFT runs at, in (0, 1].

    Returns:
        StructureMap with source "colmap"; `skipped_views` lists the views that got
        no point (no observation, or none near a keypoint).

    Raises:
        DataError: naming the view when an entry is not a MapView or its pose is not
            finite, or when observations and views differ in number.
        ConfigError: naming the argument out of range.
    """
    checked_views(views)
    max_features = integer_at_least("max_features", max_features, 1)
    radius = checked_radius(radius_px)
    image_scale = checked_image_scale(image_scale)
    if len(observations) != len(views):
        raise DataError(
            f"{len(views)} map views but {len(observations)} observation sets; one per view"
        )
    features, points, poses, cameras, names, skipped = [], [], [], [], [], []
    progress = Progress(len(views), "map structure from COLMAP points", quiet=quiet)
    for number in range(len(views)):
        view = checked_view(number, views[number])
        seen = observations[number]
        if seen is not None and not isinstance(seen, PointObservations):
            raise DataError(
                f"observations[{number}] ({view.name!r}) must be PointObservations or None"
            )
        found = on_descriptor_grid(extract_rootsift(view.image, max_features, image_scale))
        lifted = np.full((len(found), 3), np.nan, dtype=np.float32)
        if seen is None or not len(seen):
            skipped.append(SkippedView(view.name, "the COLMAP model observed no point in it"))
        else:
            rows = nearest_observations(found.keypoints, seen.keypoints, radius)
            has_point = rows >= 0
            lifted[has_point] = seen.points[rows[has_point]]
            if not has_point.any():
                skipped.append(
                    SkippedView(
                        view.name,
                        f"no keypoint within {radius:g} px of its {len(seen)} COLMAP observations",
                    )
                )
        features.append(found)
        points.append(lifted)
        poses.append(view.pose)
        cameras.append(view.camera)
        names.append(view.name)
        progress.advance()
    progress.close()
    return StructureMap(
        features=tuple(features),
        points=tuple(points),
        poses=tuple(poses),
        cameras=tuple(cameras),
        names=tuple(names),
        source="colmap",
        skipped_views=tuple(skipped),
    )
