"""What refine=features reads of its map images besides the structure itself: the
one camera queries default to, whether depth files or a COLMAP model's observations
exist, the builder's parameters, and the digests of pixels, depth files and
observations that the structure cache's key is made of (plugins/features_refiner.py,
`settings`)."""

from __future__ import annotations

import hashlib
import inspect
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError
from relocfw.core.refinement import MapImage
from relocfw.core.standardise import ZScore, check_features, k_nearest
from relocfw.structure.tracks import TrackSettings
from relocfw.structure.triangulated_structure import TRIANGULATION_METHODS
from relocfw.structure.two_view_structure import (
    build_by_two_view_triangulation,
    median_camera_spacing,
)

# On a map that is not metric, the smallest triangulation baseline as a share of the
# median distance between neighbouring map images (see plugins/features_refiner.py).
NON_METRIC_BASELINE_SHARE = 0.5


def checked_triangulation(values: Mapping[str, Any] | None) -> dict[str, Any]:
    """refine.triangulation as plain, checked values: {"method": ..., settings}.

    None gives the defaults (method tracks, TrackSettings()). Every key must be
    "method" or a TrackSettings field, each in range; a ConfigError names the first
    that is not (refine.triangulation.<key>), before any training. With method
    two_view the track settings are checked but not used: that builder runs at its
    own defaults (`builder_parameters`), as the rows it is compared with did.
    """
    if values is None:
        values = {}
    if not isinstance(values, Mapping):
        raise ConfigError(f"refine.triangulation must be a mapping of settings, got {values!r}")
    settings = dict(values)
    method = settings.pop("method", "tracks")
    if method not in TRIANGULATION_METHODS:
        choices = ", ".join(TRIANGULATION_METHODS)
        raise ConfigError(f"refine.triangulation.method must be one of {choices}, got {method!r}")
    checked = TrackSettings.of(settings, prefix="refine.triangulation")
    return {"method": method, **asdict(checked)}


def builder_parameters(
    structure: str,
    metric: bool,
    views: Sequence[MapImage],
    triangulation: Mapping[str, Any] | None = None,
) -> dict:
    """The keyword arguments the builder gets besides views, max_features, quiet and
    image_scale:
    none for structure=depth and colmap (the refiner adds its radius_px); for
    triangulated with method tracks, the checked track settings (all scale-free); for
    method two_view, every parameter of build_by_two_view_triangulation at its default
    (so a changed default changes the cache key), with the smallest baseline scaled to
    a map that is not metric."""
    if structure != "triangulated":
        return {}
    settings = checked_triangulation(triangulation)
    if settings["method"] == "tracks":
        return settings
    parameters = {
        name: parameter.default
        for name, parameter in inspect.signature(build_by_two_view_triangulation).parameters.items()
        # image_scale is the refiner's own option, passed to every builder.
        if name not in ("views", "max_features", "quiet", "image_scale")
    }
    if not metric:
        spacing = median_camera_spacing([view.pose for view in views])
        parameters["min_baseline_m"] = NON_METRIC_BASELINE_SHARE * spacing
    return {"method": "two_view", **parameters}


def structure_settings(
    structure: str, max_features: int, views: Sequence[MapImage], parameters: dict
) -> dict:
    """What the map's structure depends on besides names, poses and cameras (its
    cache key): the builder and every parameter it is called with, each image's
    pixels, and each depth file's scale and contents, so new or changed depth
    maps, re-rendered images or other build parameters are never answered from an
    old cache; for structure=colmap each image's observed pixels, points and track
    ids too (a re-triangulated model). (relocfw.structure.structure_key adds the
    OpenCV and relocfw versions.)"""
    settings = {
        "structure": structure,
        "max_features": max_features,
        "build": parameters,
        "images": [image_digest(v.image) for v in views],
        "depth": [depth_file_state(v) for v in views],
    }
    if structure == "colmap":
        # Only here, so the keys of maps built from depth or by triangulation stay
        # what they were (their caches are still found).
        settings["observations"] = [observations_digest(v) for v in views]
    return settings


def observations_digest(view: MapImage) -> str | None:
    """A short hash of a map image's COLMAP observations (pixels, points, track ids),
    None when it has none."""
    observations = getattr(view, "observations", None)
    if observations is None:
        return None
    digest = hashlib.blake2b(digest_size=8)
    for array in (observations.keypoints, observations.points, observations.track_ids):
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def has_observations(frame: object) -> bool:
    """Whether a map image (a Frame or MapImage) carries a COLMAP model's observations
    of at least one 3-D point."""
    observations = getattr(frame, "observations", None)
    return observations is not None and len(observations) > 0


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


def map_camera(views: Sequence[object], refiner: str = "refine=features") -> PinholeCamera | None:
    """The map images' one camera (queries default to it), None where they differ;
    ConfigError naming the `refiner` and the first map image without one (views:
    anything with `name` and `camera`, MapImages or relocfw.data.frames.Frames)."""
    for view in views:
        if getattr(view, "camera", None) is None:
            raise ConfigError(
                f"{refiner} needs the camera intrinsics of every map image; "
                f"{view.name} has none (the dataset gives no intrinsics for it)"
            )
    cameras = {view.camera for view in views}
    return cameras.pop() if len(cameras) == 1 else None


def query_camera(
    refiner: str, query: PinholeCamera | None, map_camera: PinholeCamera | None
) -> PinholeCamera:
    """The camera a query is solved with: its own, else the map's one camera; a
    ConfigError naming the `refiner` where there is neither."""
    camera = query or map_camera
    if camera is None:
        raise ConfigError(
            f"{refiner} needs the query's camera: the map images have no single "
            "camera, so pass camera= to localize"
        )
    return camera


def keyframes_by_descriptor(
    zscore: ZScore, points: np.ndarray, descriptor: np.ndarray, count: int
) -> list[int]:
    """The `count` map images whose z-scored descriptors (`points`) are nearest to the
    query crop's `descriptor`, nearest first."""
    wanted = check_features(np.asarray(descriptor)[None], points.shape[1])
    _, nearest = k_nearest(zscore(wanted), points, count)
    return [int(i) for i in nearest[0]]
