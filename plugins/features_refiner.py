"""refine=features / features_rgb: local features of the query against keyframes of the
map, 2-D/3-D correspondences, absolute pose by LO-RANSAC (relocfw.structure).

The structure-based family (hloc's): per map image RootSIFT keypoints with a 3-D point
each, lifted with the map image's depth (`structure=depth`) or triangulated between
map images with their known poses (`structure=triangulated`, for users without depth).
Per query: retrieve `count` keyframes, by the chosen crop's descriptor (with crop=ga,
the paper's idea applied to retrieval) or by the network's pose, match, solve. With
fewer than `min_inliers` inliers it answers the network's pose, flagged as fallen back.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.refinement import MapImage, PoseRefiner, Refined, RefineQuery
from relocfw.core.standardise import ZScore, check_features, k_nearest
from relocfw.structure import (
    MapView,
    StructureMap,
    cached_structure_map,
    keyframes_by_pose,
    localize_against,
    structure_key,
)

STRUCTURES = ("depth", "triangulated")
KEYFRAMES = ("descriptor", "pose")


class FeaturesRefiner(PoseRefiner):
    """Local features + PnP against the map's structure.

    Args:
        structure: "depth" (3-D points from the map images' depth maps) or
            "triangulated" (between map images with their known poses; RGB only).
        keyframes: "descriptor" (the map images nearest to the chosen crop's
            descriptor) or "pose" (nearest to the network's pose, looking the same way).
        count: keyframes per query.
        max_features: most RootSIFT keypoints per image (map and query).
        ratio: Lowe's ratio test of the mutual nearest neighbours.
        max_error_px: reprojection error under which a correspondence is an inlier.
        min_inliers: fewest inliers for a pose; below, the network's pose stands.
        cache_dir: where the map's structure is cached by content (None: not cached).
        quiet: no progress bars.
    """

    def __init__(
        self,
        structure: str = "depth",
        keyframes: str = "descriptor",
        count: int = 10,
        max_features: int = 1024,
        ratio: float = 0.8,
        max_error_px: float = 8.0,
        min_inliers: int = 12,
        cache_dir: str | Path | None = None,
        quiet: bool = False,
    ) -> None:
        # Every option is checked here, before training and the map's structure, and
        # named as the command line spells it (refine.ratio, ...).
        if structure not in STRUCTURES:
            choices = ", ".join(STRUCTURES)
            raise ConfigError(f"refine.structure must be one of {choices}, got {structure!r}")
        if keyframes not in KEYFRAMES:
            choices = ", ".join(KEYFRAMES)
            raise ConfigError(f"refine.keyframes must be one of {choices}, got {keyframes!r}")
        self.structure_source = structure
        self.keyframes = keyframes
        self.count = integer_at_least("refine.count", count, 1)
        self.max_features = integer_at_least("refine.max_features", max_features, 8)
        self.ratio = positive_number("refine.ratio", ratio, most=1.0)
        self.max_error_px = positive_number("refine.max_error_px", max_error_px)
        self.min_inliers = integer_at_least("refine.min_inliers", min_inliers, 4)
        self.cache_dir = None if cache_dir is None else Path(cache_dir).expanduser()
        self.quiet = bool(quiet)

    def settings(self, views: Sequence[MapImage]) -> dict:
        """What the map's structure depends on besides names, poses and cameras (its
        cache key): the options, each image's pixels, and each depth file as it is
        now (path, scale, size, modification time), so new or changed depth maps or
        re-rendered images are never answered from an old cache."""
        return {
            "structure": self.structure_source,
            "max_features": self.max_features,
            "images": [image_digest(v.image) for v in views],
            "depth": [depth_file_state(v) for v in views],
        }

    def check_map(self, frames: Sequence[object]) -> None:
        map_camera(frames)

    def fit(self, views: Sequence[MapImage], descriptors: np.ndarray, quiet: bool = True) -> None:
        quiet = quiet or self.quiet
        self.camera = map_camera(views)
        self.zscore = ZScore().fit(check_features(descriptors))
        self.points = self.zscore(check_features(descriptors))
        self.poses = [view.pose for view in views]
        map_views = [
            MapView(
                image=view.image,
                pose=view.pose,
                camera=view.camera,
                depth_path=view.depth_path,
                name=view.name,
                depth_units_per_metre=view.depth_units_per_metre,
            )
            for view in views
        ]

        def build() -> StructureMap:
            if self.structure_source == "depth":
                return StructureMap.build_from_depth(map_views, self.max_features, quiet=quiet)
            return StructureMap.build_by_triangulation(map_views, self.max_features, quiet=quiet)

        if self.cache_dir is None:
            self.structure = build()
            return
        key = structure_key(
            [v.name for v in views], self.poses, [v.camera for v in views], self.settings(views)
        )
        self.structure = cached_structure_map(self.cache_dir, key, build, quiet)

    @property
    def skipped_views(self) -> tuple:
        """The map images that gave no 3-D point (name and reason), for reports."""
        structure = getattr(self, "structure", None)
        return tuple(structure.skipped_views) if structure is not None else ()

    def keyframes_of(self, query: RefineQuery) -> list[int]:
        count = min(self.count, len(self.poses))
        if self.keyframes == "pose":
            return list(keyframes_by_pose(self.poses, query.network_pose, count))
        features = check_features(np.asarray(query.descriptor)[None], self.points.shape[1])
        _, indices = k_nearest(self.zscore(features), self.points, count)
        return [int(i) for i in indices[0]]

    def refine(self, query: RefineQuery) -> Refined:
        if not hasattr(self, "structure"):
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        camera = query.camera or self.camera
        if camera is None:
            raise ConfigError(
                "refine=features needs the query's camera: the map images have no single "
                "camera, so pass camera= to localize"
            )
        started = time.perf_counter()
        keyframes = self.keyframes_of(query)
        retrieval = time.perf_counter() - started
        answer = localize_against(
            self.structure,
            query.image,
            camera,
            keyframes,
            max_features=self.max_features,
            ratio=self.ratio,
            max_error_px=self.max_error_px,
            min_inliers=self.min_inliers,
        )
        seconds = {"retrieval": retrieval, **answer.seconds}
        if not answer.success:
            return Refined(query.network_pose, float(answer.inliers), True, seconds)
        return Refined(answer.pose, float(answer.inliers), False, seconds)


def image_digest(image: np.ndarray) -> str:
    """A short hash of an image's pixels (about a second for 400 VGA images)."""
    return hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=8).hexdigest()


def depth_file_state(view: MapImage) -> list:
    """A depth file as the cache key sees it: path, scale, and size and modification
    time when it exists."""
    if view.depth_path is None:
        return [None]
    path = Path(view.depth_path)
    stat = path.stat() if path.is_file() else None
    state = [stat.st_size, stat.st_mtime_ns] if stat is not None else ["missing"]
    return [str(path), view.depth_units_per_metre, *state]


def map_camera(views: Sequence[object]) -> PinholeCamera | None:
    """The map images' one camera (queries default to it), None where they differ;
    ConfigError naming the first map image without one (views: anything with `name`
    and `camera`, MapImages or relocfw.data.frames.Frames)."""
    for view in views:
        if view.camera is None:
            raise ConfigError(
                f"refine=features needs the camera intrinsics of every map image; "
                f"{view.name} has none (the dataset gives no intrinsics for it)"
            )
    cameras = {view.camera for view in views}
    return cameras.pop() if len(cameras) == 1 else None
