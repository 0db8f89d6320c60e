"""A structure map from RGB map images of known pose by multi-view tracks, triangulated
over all their views with the poses held fixed (relocfw.structure.tracks)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from relocfw.core.options import integer_at_least
from relocfw.core.progress import Progress
from relocfw.structure.map_view import MapView
from relocfw.structure.structure_map import SkippedView, StructureMap
from relocfw.structure.tracks import TrackSettings, build_track_points
from relocfw.structure.view_features import checked_views, features_of_views


def build_by_track_triangulation(
    views: Sequence[MapView],
    max_features: int = 1024,
    quiet: bool = False,
    image_scale: float = 1.0,
    **settings: Any,
) -> StructureMap:
    """The structure of RGB map images of known pose, from multi-view tracks.

    Partners chosen for geometry (covisible, a useful ray angle at the scene depth),
    epipolar-filtered matches joined into tracks, each track triangulated over all
    its views with outlier views dropped and the poses held fixed
    (relocfw.structure.tracks); every keypoint of a track shares its one point.

    Args:
        views: the map images (M), each with pose and camera (depth is not read).
        max_features: the most keypoints per image (>= 1).
        quiet: show no progress bar.
        image_scale: the share of each side SIFT runs at, in (0, 1].
        **settings: TrackSettings fields (partners, min_partner_angle_deg,
            max_partner_angle_deg, epipolar_px, max_reprojection_px, min_views,
            min_angle_deg, ratio); the rest keep their defaults.

    Returns:
        StructureMap with source "triangulated"; `skipped_views` lists images with
        no partner or no kept track.

    Raises:
        DataError: naming the view when an entry is not a MapView or its pose is not
            finite.
        ConfigError: naming the setting that is unknown or out of range.
    """
    checked_views(views)
    max_features = integer_at_least("max_features", max_features, 1)
    # Checked before the slow part, so a wrong setting fails at once.
    checked = TrackSettings.of(settings, prefix="triangulation")
    # Two phases, each counting the map's images: features, then matching each image
    # with its partners (the slow part; triangulating the tracks after it is quick).
    count = len(views)
    progress = Progress(count, "map structure by tracks (features)", quiet=quiet)
    features, poses, cameras, names = features_of_views(views, max_features, progress, image_scale)
    progress.close()
    progress = Progress(count, "map structure by tracks (matching)", quiet=quiet)
    points, partners = build_track_points(features, poses, cameras, checked, progress)
    progress.close()
    skipped = []
    for name, chosen, rows in zip(names, partners, points, strict=True):
        if not chosen:
            reason = "no partner view (none covisible within the partner angles)"
            skipped.append(SkippedView(name, reason))
        elif not np.isfinite(rows).all(axis=1).any():
            skipped.append(SkippedView(name, f"no track kept with {len(chosen)} partner(s)"))
    return StructureMap(
        features=tuple(features),
        points=tuple(points),
        poses=tuple(poses),
        cameras=tuple(cameras),
        names=tuple(names),
        source="triangulated",
        skipped_views=tuple(skipped),
    )
