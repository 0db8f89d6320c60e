"""refine=features / features_rgb: local features of the query against keyframes of the
map, 2-D/3-D correspondences, absolute pose by LO-RANSAC (relocfw.structure).

The structure-based family (hloc's): per map image RootSIFT keypoints with a 3-D point
each, lifted with the map image's depth (`structure=depth`) or triangulated between
map images with their known poses (`structure=triangulated`, for users without depth).
Per query: retrieve `count` keyframes, by the chosen crop's descriptor (with crop=ga,
the paper's idea applied to retrieval) or by the network's pose, match, solve. With
fewer than `min_inliers` inliers it answers the network's pose, flagged as fallen back;
so it does when the network's pose is not finite and keyframes are chosen by it (no
keyframe is near a NaN pose: the refiner cannot do better than the network, which is
the contract's fallback, and one broken query does not stop an evaluation).

On a map that is not metric (refine.metric=false, set from dataset.metric: an
unaligned COLMAP model), the triangulation's one length in metres, the 5 cm smallest
baseline, is measured against the map instead: half the median distance between a
map image and its nearest other map image (the bound's job is to skip partners
standing almost where the image stands, and in a map of unknown scale "almost" can
only be told from how far apart its images usually are). structure=depth is refused
there: depth maps are in metres and cannot be lifted into poses that are not.

Model files (format 5) keep the fitted refiner whole (`state` / `load_state`: the map's
structure as flat arrays, relocfw.structure.map_state, the keyframe descriptors and
the query options), so a loaded model needs no map image, depth file or cache.
"""

from __future__ import annotations

import hashlib
import inspect
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.refinement import MapImage, PoseRefiner, Refined, RefineQuery
from relocfw.core.standardise import ZScore, check_features, k_nearest
from relocfw.structure import (
    MapView,
    StructureMap,
    build_by_triangulation,
    cached_structure_map,
    keyframes_by_pose,
    localize_against,
    structure_key,
)
from relocfw.structure.map_state import checked_tensor, map_of_state, map_state
from relocfw.structure.structure_map import median_camera_spacing

STRUCTURES = ("depth", "triangulated")
KEYFRAMES = ("descriptor", "pose")
# On a map that is not metric, the smallest triangulation baseline as a share of the
# median distance between neighbouring map images (see the module's note).
NON_METRIC_BASELINE_SHARE = 0.5
# The query options a state keeps (the fitted refiner's, so a file saved without its
# options still answers as the run did), integers and numbers.
STATE_INTEGERS = {"count": 1, "max_features": 8, "min_inliers": 4}  # and their least
STATE_NUMBERS = ("ratio", "max_error_px")
STATE_LABEL = "refine=features state"
NO_DEPTH_HINT = (
    "use refine=features_rgb, which triangulates the map's points from its images and poses"
)


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
        metric: whether the map's poses are in metres (dataset.metric); False scales
            the triangulation's metric bound to the map and refuses structure=depth.
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
        metric: bool = True,
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
        if not isinstance(metric, bool):
            raise ConfigError(f"refine.metric must be true or false, got {metric!r}")
        self.metric = metric
        if structure == "depth" and not metric:
            raise ConfigError(
                "refine=features lifts depth maps (metres) into the map's poses, which "
                f"are not metric here (dataset.metric=false); {NO_DEPTH_HINT}"
            )

    def settings(self, views: Sequence[MapImage], parameters: dict | None = None) -> dict:
        """What the map's structure depends on besides names, poses and cameras (its
        cache key): the builder and every parameter it is called with, each image's
        pixels, and each depth file's scale and contents, so new or changed depth
        maps, re-rendered images or other build parameters are never answered from an
        old cache. (relocfw.structure.structure_key adds the OpenCV and relocfw
        versions.) `parameters`: build_parameters(views), where the caller has them
        already (a non-metric map's camera spacing is O(M^2) to find)."""
        if parameters is None:
            parameters = self.build_parameters(views)
        return {
            "structure": self.structure_source,
            "max_features": self.max_features,
            "build": parameters,
            "images": [image_digest(v.image) for v in views],
            "depth": [depth_file_state(v) for v in views],
        }

    def build_parameters(self, views: Sequence[MapImage]) -> dict:
        """The keyword arguments the builder gets besides views, max_features and quiet:
        none for structure=depth; for triangulated, every parameter of
        build_by_triangulation at its default (so a changed default changes the cache
        key), with the smallest baseline scaled to a map that is not metric."""
        if self.structure_source == "depth":
            return {}
        parameters = {
            name: parameter.default
            for name, parameter in inspect.signature(build_by_triangulation).parameters.items()
            if name not in ("views", "max_features", "quiet")
        }
        if not self.metric:
            spacing = median_camera_spacing([view.pose for view in views])
            parameters["min_baseline_m"] = NON_METRIC_BASELINE_SHARE * spacing
        return parameters

    def check_map(self, frames: Sequence[object]) -> None:
        map_camera(frames)
        if self.structure_source == "depth" and not any(has_depth_file(f) for f in frames):
            raise ConfigError(
                f"refine=features needs depth maps, and none of the {len(frames)} map "
                f"images has one; {NO_DEPTH_HINT}"
            )

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

        parameters = self.build_parameters(views)

        def build() -> StructureMap:
            if self.structure_source == "depth":
                return StructureMap.build_from_depth(map_views, self.max_features, quiet=quiet)
            return StructureMap.build_by_triangulation(
                map_views, self.max_features, quiet=quiet, **parameters
            )

        if self.cache_dir is None:
            self.structure = build()
        else:
            key = structure_key(
                [v.name for v in views],
                self.poses,
                [v.camera for v in views],
                self.settings(views, parameters),
            )
            self.structure = cached_structure_map(self.cache_dir, key, build, quiet)
        if self.structure_source == "depth" and not self.structure.point_counts().any():
            # Every query would fall back: a configuration that cannot work.
            raise ConfigError(
                f"refine=features found no usable depth in any of the {len(views)} map "
                f"images (first: {self.skipped_views[0].name}: "
                f"{self.skipped_views[0].reason}); {NO_DEPTH_HINT}"
            )

    @property
    def skipped_views(self) -> tuple:
        """The map images that gave no 3-D point (name and reason), for reports."""
        structure = getattr(self, "structure", None)
        return tuple(structure.skipped_views) if structure is not None else ()

    def state(self) -> dict[str, torch.Tensor]:
        """Everything a query uses, as plain tensors (relocfw.structure.map_state: every
        map image's uint8 descriptors, keypoints, the 3-D points of the keypoints that
        have one, poses and cameras), plus the standardisation and the z-scored map
        descriptors that keyframes are retrieved by, and the query options. A refiner
        loaded from it needs no map image, depth file or cache."""
        if not hasattr(self, "structure"):
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        options = {key: torch.tensor(int(getattr(self, key))) for key in STATE_INTEGERS}
        options |= {
            key: torch.tensor(float(getattr(self, key)), dtype=torch.float64)
            for key in STATE_NUMBERS
        }
        return {
            **map_state(self.structure),
            **self.zscore.state(),
            "keyframe_descriptors": torch.from_numpy(np.array(self.points, dtype=np.float64)),
            "keyframes": torch.tensor(KEYFRAMES.index(self.keyframes)),
            **options,
        }

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """What `state` returned: the refiner is then fitted. Every tensor is checked
        before anything is kept (a model file is data from anyone); a fault is one
        DataError naming the tensor."""
        structure = map_of_state(state, STATE_LABEL)
        keyframe_points = checked_tensor(state, "keyframe_descriptors", torch.float64, STATE_LABEL)
        if keyframe_points.ndim != 2 or len(keyframe_points) != len(structure):
            raise DataError(
                f"{STATE_LABEL}: keyframe_descriptors must be [{len(structure)}, D], one "
                f"row per map image, got {list(keyframe_points.shape)}"
            )
        if not np.isfinite(keyframe_points).all():
            raise DataError(f"{STATE_LABEL}: keyframe_descriptors hold NaN or infinite values")
        zscore = ZScore().load_state(state)
        if zscore.mean.shape != (keyframe_points.shape[1],):
            raise DataError(
                f"{STATE_LABEL}: mean and std must hold {keyframe_points.shape[1]} values, "
                f"one per descriptor dimension, got {zscore.mean.shape[0]}"
            )
        options = stored_options(state)
        for key, value in options.items():
            setattr(self, key, value)
        self.structure = structure
        self.zscore = zscore
        self.points = keyframe_points
        self.poses = list(structure.poses)
        cameras = set(structure.cameras)
        self.camera = cameras.pop() if len(cameras) == 1 else None
        self.structure_source = structure.source

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
        if self.keyframes == "pose" and not query.network_pose.is_finite:
            # No map image is near a NaN pose; the network's answer stands, flagged.
            return Refined(query.network_pose, 0.0, True, {"retrieval": 0.0})
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


def stored_options(state: dict[str, torch.Tensor]) -> dict:
    """The query options a state keeps, each checked as the command line's would be;
    an option the state lacks keeps the constructor's."""
    options: dict = {}
    try:
        if "keyframes" in state:
            code = int(checked_tensor(state, "keyframes", torch.int64, STATE_LABEL))
            if not 0 <= code < len(KEYFRAMES):
                raise DataError(f"{STATE_LABEL}: keyframes must be 0 or 1, got {code}")
            options["keyframes"] = KEYFRAMES[code]
        for key in STATE_INTEGERS:
            if key in state:
                value = int(checked_tensor(state, key, torch.int64, STATE_LABEL))
                options[key] = integer_at_least(f"refine.{key}", value, STATE_INTEGERS[key])
        for key in STATE_NUMBERS:
            if key in state:
                value = float(checked_tensor(state, key, torch.float64, STATE_LABEL))
                options[key] = positive_number(
                    f"refine.{key}", value, **({"most": 1.0} if key == "ratio" else {})
                )
    except (ConfigError, TypeError, ValueError) as error:
        raise DataError(f"{STATE_LABEL}: {error}") from None
    return options


def image_digest(image: np.ndarray) -> str:
    """A short hash of an image's pixels (about a second for 400 VGA images)."""
    return hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=8).hexdigest()


def depth_file_state(view: MapImage) -> list:
    """A depth file as the cache key sees it: path, scale, and a hash of its bytes
    when it exists (size and modification time miss a file copied over another with
    its times kept)."""
    if view.depth_path is None:
        return [None]
    path = Path(view.depth_path)
    state = file_digest(path) if path.is_file() else "missing"
    return [str(path), view.depth_units_per_metre, state]


def file_digest(path: Path) -> str:
    """A short hash of a file's bytes (a 7-Scenes depth PNG: about 0.2 ms)."""
    return hashlib.blake2b(path.read_bytes(), digest_size=8).hexdigest()


def has_depth_file(frame: object) -> bool:
    """Whether a map image (a Frame or MapImage) names a depth file that exists."""
    path = getattr(frame, "depth_path", None)
    return path is not None and Path(path).is_file()


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
