"""refine=relative: the keyframe-based family, relative poses to retrieved keyframes.

The seed paper's first family of relocalizers: select the most similar keyframes,
estimate the query's pose relative to each, transfer it to the world frame. Per query:

1. retrieve the `count` map images nearest to the chosen crop's descriptor (as
   refine=features' keyframes=descriptor does, through a z-scored copy of the map's
   descriptors);
2. match the query's RootSIFT features against each keyframe's
   (relocfw.structure.matching: mutual nearest neighbours with Lowe's ratio test);
3. per keyframe with `min_inliers` matches or more, the essential matrix by PoseLib's
   5-point LO-RANSAC (Sampson error under `max_error_px`), its rotation and the
   direction of its translation (relocfw.structure.relative_pose, which says why
   PoseLib); a pair whose inliers move less than `min_parallax_deg` between the two
   views (no baseline) gives no direction and is not used;
4. the query's centre where the keyframes' rays towards it meet (least squares, by
   consensus over pairs of rays: scale-free, no depth and no 3-D point needed), its
   rotation the inlier-weighted mean of the agreeing keyframes' rotations.

Fallback: the network's pose, flagged (fell_back=True), never an exception, whenever
the geometry cannot place the query: fewer than `min_keyframes` keyframes with a
usable relative pose, rays that do not cross at `min_ray_angle_deg` (all keyframes on
one line with the query, or too close together for their distance to it), or rays
that do not agree on one point within `max_ray_error_deg`.

Confidence: the total inliers of the keyframes the position rests on (0 on a
fallback): distinct matches, since a keypoint is matched at most once per keyframe.

The map: per map image only keypoints, RootSIFT descriptors, pose and camera. It is
kept in relocfw.structure's StructureMap with every 3-D point NaN, because that is the
container the rest of the structure code already reads, saves and checks: its
content-keyed cache (`cached_structure_map`, so a map's features are extracted once
per content, not per run) and its model-file encoding (relocfw.structure.map_state:
uint8 descriptors, offsets, every tensor checked on loading, and a map without points
costs no bytes for them). Its `source` says "triangulated" in the sense that matters
to a reader of the map, RGB only, no depth read; `point_counts()` shows it holds no
point. A dedicated container would have duplicated the encoding and its checks.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import check_rgb_image
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.progress import Progress
from relocfw.core.refinement import MapImage, PoseRefiner, Refined, RefineQuery
from relocfw.core.sensor_poses import (
    colour_pose,
    map_pose_to_colour,
    pose_to_colour_state,
    reference_pose,
    stored_pose_to_colour,
)
from relocfw.core.standardise import ZScore, check_features
from relocfw.core.values import Pose
from relocfw.structure.features import extract_rootsift
from relocfw.structure.map_state import checked_tensor, map_of_state, map_state
from relocfw.structure.matching import match_against_views
from relocfw.structure.refiner_inputs import (
    image_digest,
    keyframes_by_descriptor,
    map_camera,
    query_camera,
)
from relocfw.structure.refiner_state import MOST_KEYFRAMES, MOST_SIZES, checked_size
from relocfw.structure.relative_pose import (
    QueryRay,
    locate_by_rays,
    mean_rotation,
    query_ray,
    solve_relative_pose,
)
from relocfw.structure.structure_cache import cached_structure_map, structure_key
from relocfw.structure.structure_map import StructureMap, on_descriptor_grid

STATE_LABEL = "refine=relative state"
# The options a state keeps: integers with their least values, numbers with their
# largest (None: none). The size-like ones (MOST_SIZES) are bounded above as
# refine=features' are: a model file is data from anyone, and a forged size must be
# refused on loading, not reach OpenCV (SIFT with 2**40 features raises at every
# query); min_keyframes cannot mean more than the most keyframes a query retrieves.
INTEGER_OPTIONS = {"count": 1, "max_features": 8, "min_inliers": 5, "min_keyframes": 2}
NUMBER_OPTIONS = {
    "ratio": 1.0,
    "max_error_px": None,  # bounded as a size (MOST_SIZES), as refine=features' is
    "min_parallax_deg": 90.0,
    "min_ray_angle_deg": 90.0,
    "max_ray_error_deg": 90.0,
}


def checked_options(options: dict) -> dict:
    """Every query option checked and named as the command line spells it."""
    checked = {}
    for key, least in INTEGER_OPTIONS.items():
        if key in MOST_SIZES:
            checked[key] = checked_size(key, options[key], least)
            continue
        checked[key] = integer_at_least(f"refine.{key}", options[key], least)
        if checked[key] > MOST_KEYFRAMES:
            raise ConfigError(
                f"refine.{key} must be at most {MOST_KEYFRAMES}, got {options[key]!r}"
            )
    for key, most in NUMBER_OPTIONS.items():
        if key in MOST_SIZES:
            checked[key] = checked_size(key, options[key])
        else:
            checked[key] = positive_number(f"refine.{key}", options[key], most=most)
    return checked


def keyframe_map(
    views: Sequence[MapImage], poses: Sequence[Pose], max_features: int, quiet: bool
) -> StructureMap:
    """Each map image's RootSIFT features (on the stored uint8 grid, so the map in
    memory matches as it will after a save), its colour camera's pose (`poses`) and
    camera; no 3-D point."""
    features = []
    progress = Progress(len(views), "keyframe features", quiet=quiet)
    for view in views:
        features.append(on_descriptor_grid(extract_rootsift(view.image, max_features)))
        progress.advance()
    progress.close()
    return StructureMap(
        features=tuple(features),
        points=tuple(np.full((len(f), 3), np.nan, dtype=np.float32) for f in features),
        poses=tuple(poses),
        cameras=tuple(view.camera for view in views),
        names=tuple(view.name for view in views),
        source="triangulated",
    )


class RelativeRefiner(PoseRefiner):
    """Relative poses to retrieved keyframes, the position where their rays meet.

    Args:
        count: keyframes retrieved per query.
        max_features: most RootSIFT keypoints per image (map and query).
        ratio: Lowe's ratio test of the mutual nearest neighbours.
        max_error_px: Sampson (epipolar) error of an inlier, in pixels.
        min_inliers: fewest inliers of a keyframe's relative pose for it to be used.
        min_keyframes: fewest keyframes whose rays agree for a position (>= 2).
        min_parallax_deg: least median parallax of a pair's inliers for its
            translation direction to be used (a shorter baseline gives noise).
        min_ray_angle_deg: least angle at which two rays must cross, and the
            keyframes subtend at their crossing, for it to place the query.
        max_ray_error_deg: how far a ray may point from the position and agree.
        cache_dir: where the map's features are cached by content (None: not cached).
        quiet: no progress bars.
    """

    def __init__(
        self,
        count: int = 10,
        max_features: int = 1024,
        ratio: float = 0.8,
        max_error_px: float = 2.0,
        min_inliers: int = 12,
        min_keyframes: int = 2,
        min_parallax_deg: float = 1.0,
        min_ray_angle_deg: float = 3.0,
        max_ray_error_deg: float = 5.0,
        cache_dir: str | Path | None = None,
        quiet: bool = False,
    ) -> None:
        options = checked_options(
            {
                "count": count,
                "max_features": max_features,
                "min_inliers": min_inliers,
                "min_keyframes": min_keyframes,
                "ratio": ratio,
                "max_error_px": max_error_px,
                "min_parallax_deg": min_parallax_deg,
                "min_ray_angle_deg": min_ray_angle_deg,
                "max_ray_error_deg": max_ray_error_deg,
            }
        )
        for key, value in options.items():
            setattr(self, key, value)
        self.cache_dir = None if cache_dir is None else Path(cache_dir).expanduser()
        self.quiet = bool(quiet)

    def options(self) -> dict:
        return {key: getattr(self, key) for key in (*INTEGER_OPTIONS, *NUMBER_OPTIONS)}

    def check_map(self, frames: Sequence[object]) -> None:
        map_camera(frames, "refine=relative")

    def fit(self, views: Sequence[MapImage], descriptors: np.ndarray, quiet: bool = True) -> None:
        quiet = quiet or self.quiet
        features = check_features(descriptors)
        if len(views) != len(features):
            raise DataError(f"fit: {len(views)} map images but {len(features)} descriptors")
        camera = map_camera(views, "refine=relative")
        zscore = ZScore().fit(features)
        # Rays leave the colour cameras that took the images; the answer goes back to
        # the sensor the dataset's poses describe (relocfw.core.sensor_poses).
        pose_to_colour = map_pose_to_colour(views, "refine=relative")
        poses = [colour_pose(view.pose, pose_to_colour) for view in views]

        def build() -> StructureMap:
            return keyframe_map(views, poses, self.max_features, quiet)

        if self.cache_dir is None:
            structure = build()
        else:
            settings = {
                "structure": "keyframe features",
                "max_features": self.max_features,
                "images": [image_digest(v.image) for v in views],
            }
            key = structure_key([v.name for v in views], poses, [v.camera for v in views], settings)
            structure = cached_structure_map(self.cache_dir, key, build, quiet)
        self.camera = camera
        self.zscore = zscore
        self.points = zscore(features)
        self.structure = structure
        self.pose_to_colour = pose_to_colour

    def refine(self, query: RefineQuery) -> Refined:
        if not hasattr(self, "structure"):
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        camera = query_camera("refine=relative", query.camera, self.camera)
        started = time.perf_counter()
        count = min(self.count, len(self.structure))
        keyframes = keyframes_by_descriptor(self.zscore, self.points, query.descriptor, count)
        retrieved = time.perf_counter()
        check_rgb_image(query.image, "query image")
        height, width = query.image.shape[:2]
        if (width, height) != (camera.width, camera.height):
            raise DataError(
                f"the query image is {width}x{height} but its camera is "
                f"{camera.width}x{camera.height}"
            )
        features = extract_rootsift(query.image, self.max_features)
        extracted = time.perf_counter()
        views = [self.structure.features[i] for i in keyframes]
        matches = match_against_views(features, views, self.ratio)
        matched = time.perf_counter()
        rays = self.rays_of(features.keypoints, keyframes, matches, camera)
        located = locate_by_rays(
            rays, self.min_keyframes, self.min_ray_angle_deg, self.max_ray_error_deg
        )
        used = [rays[i] for i in located.used]
        confidence = float(sum(ray.weight for ray in used)) if located.position is not None else 0.0
        if located.position is None:
            pose, fell_back = query.network_pose, True
        else:
            solved = Pose(located.position, mean_rotation(used))
            pose, fell_back = reference_pose(solved, self.pose_to_colour), False
        seconds = {
            "retrieval": retrieved - started,
            "features": extracted - retrieved,
            "matching": matched - extracted,
            "solve": time.perf_counter() - matched,
        }
        return Refined(pose, confidence, fell_back, seconds)

    def rays_of(
        self,
        query_keypoints: np.ndarray,
        keyframes: list[int],
        matches: list[tuple[int, np.ndarray]],
        camera: PinholeCamera,
    ) -> list[QueryRay]:
        """One world ray per keyframe whose relative pose is found with a baseline."""
        rays = []
        for slot, pairs in matches:
            if len(pairs) < self.min_inliers:
                continue  # cannot reach min_inliers: skip the solve
            index = keyframes[slot]
            relative = solve_relative_pose(
                self.structure.features[index].keypoints[pairs[:, 1]],
                query_keypoints[pairs[:, 0]],
                self.structure.cameras[index],
                camera,
                self.max_error_px,
                self.min_inliers,
            )
            if relative.success and relative.parallax_deg >= self.min_parallax_deg:
                rays.append(query_ray(self.structure.poses[index], relative))
        return rays

    def state(self) -> dict[str, torch.Tensor]:
        """The map's features, poses and cameras (relocfw.structure.map_state), the
        standardisation and the z-scored map descriptors keyframes are retrieved by,
        and the query options: a loaded refiner needs no map image or cache."""
        if not hasattr(self, "structure"):
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        options = self.options()
        return {
            **map_state(self.structure),
            **self.zscore.state(),
            "keyframe_descriptors": torch.from_numpy(np.array(self.points, dtype=np.float64)),
            **{key: torch.tensor(int(options[key])) for key in INTEGER_OPTIONS},
            **{
                key: torch.tensor(float(options[key]), dtype=torch.float64)
                for key in NUMBER_OPTIONS
            },
            **pose_to_colour_state(self.pose_to_colour),
        }

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """What `state` returned. Every tensor is checked before anything is kept (a
        model file is data from anyone); a fault is one DataError naming it."""
        structure = map_of_state(state, STATE_LABEL)
        points = checked_tensor(state, "keyframe_descriptors", torch.float64, STATE_LABEL)
        if points.ndim != 2 or len(points) != len(structure) or not np.isfinite(points).all():
            raise DataError(
                f"{STATE_LABEL}: keyframe_descriptors must be [{len(structure)}, D] finite "
                f"values, one row per map image, got {list(points.shape)}"
            )
        zscore = ZScore().load_state(state)
        if zscore.mean.shape != (points.shape[1],):
            raise DataError(
                f"{STATE_LABEL}: mean and std must hold {points.shape[1]} values, one per "
                "descriptor dimension"
            )
        pose_to_colour = stored_pose_to_colour(state, STATE_LABEL)
        options = self.options()
        try:
            for key in INTEGER_OPTIONS:
                if key in state:
                    options[key] = int(checked_tensor(state, key, torch.int64, STATE_LABEL))
            for key in NUMBER_OPTIONS:
                if key in state:
                    options[key] = float(checked_tensor(state, key, torch.float64, STATE_LABEL))
            options = checked_options(options)
        except (ConfigError, TypeError, ValueError) as error:
            raise DataError(f"{STATE_LABEL}: {error}") from None
        for key, value in options.items():
            setattr(self, key, value)
        cameras = set(structure.cameras)
        self.camera = cameras.pop() if len(cameras) == 1 else None
        self.zscore = zscore
        self.points = points
        self.structure = structure
        self.pose_to_colour = pose_to_colour
