"""The map's structure: each map image's local features and a 3-D point per keypoint.

Structure-based relocalization (as hloc does it) matches a query's local features
against a few map images and solves the query's pose from the 2-D/3-D
correspondences; this module builds what it matches against. Two builders:

- `build_from_depth`: each keypoint is lifted to 3-D with the image's depth map
  (RGB-D maps such as 7-Scenes);
- `build_by_triangulation`: RGB only; by default each keypoint's point is its
  multi-view track's, triangulated over every map image that sees it with the known
  poses held fixed (`build_by_track_triangulation`, relocfw.structure.tracks); the
  earlier two-view medians stay available (`build_by_two_view_triangulation`,
  method "two_view") for comparisons.

A third, `relocfw.structure.colmap_structure.build_from_colmap_points`, gives the
keypoints a COLMAP model's own 3-D points (source "colmap").

A map is one compressed npz file (`StructureMap.save` / `StructureMap.load`), and
`cached_structure_map` keeps one per content key (`structure_key`) under a cache
folder, so a map is built once.

Descriptors are kept quantised: RootSIFT components lie in [0, 1] and are stored as
round(255 x value) in uint8, a quarter of float32's space. The builders put the
descriptors on that grid when they make the map, so the map in memory is exactly the
map on disk (a map saved and loaded gives the same matches, bit for bit). Measured on
20 pairs of Red Kitchen training frames five apart (benchmarks/structure_query.py
--check-quantisation), 0.28% of the 6069 float32 mutual ratio-test matches were lost
and 0.13% new ones appeared: matches near the ratio bound.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import math
import re
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from relocfw.core.atomic_files import atomic_write, remove_stale_temporaries
from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import integer_at_least
from relocfw.core.progress import Progress
from relocfw.core.values import Pose
from relocfw.core.version import VERSION
from relocfw.data.depth import check_depth_range, read_depth
from relocfw.structure.covisibility import optical_axes
from relocfw.structure.features import (
    SIFT_DIMENSIONS,
    LocalFeatures,
    checked_image_scale,
    extract_rootsift,
)
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.map_view import MapView
from relocfw.structure.matching import checked_ratio, match_against_views
from relocfw.structure.registration import register_depth
from relocfw.structure.tracks import TrackSettings, build_track_points
from relocfw.structure.triangulation import checked_bound, triangulate

# Bump when the file layout changes: it is part of every structure_key, so a cached
# map written by older code is never picked up by code that reads it differently.
FORMAT_VERSION = 1
FILE_KIND = "relocfw structure map"
SOURCES = ("depth", "triangulated", "colmap")
TRIANGULATION_METHODS = ("tracks", "two_view")
# RootSIFT components are in [0, 1]; uint8 steps of 1/255 (an error of at most 0.002
# per component, against nearest-neighbour distances of 0.3 and more).
DESCRIPTOR_SCALE = 255.0
# A depth map may have another resolution than its image when it covers the same
# field of view: scaled to the image's width, its height may be off by this much.
ASPECT_TOLERANCE_PX = 1.0
KEY_PATTERN = re.compile(r"[0-9a-f]{8,64}")


@dataclass(frozen=True)
class SkippedView:
    """A map view that gave no 3-D point, and why (callers report these).

    Attributes:
        name: the view's name (MapView.name).
        reason: e.g. "no depth map (depth_path is None)" or the read error.
    """

    name: str
    reason: str


def quantised(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT descriptors as uint8 steps of 1/255.

    Args:
        descriptors: [N, D] values in [0, 1] (RootSIFT's range).

    Returns:
        [N, D] uint8, round(255 x value).

    Raises:
        DataError: when a value lies outside [0, 1] (not RootSIFT; storing it would
            clip it silently).
    """
    values = np.asarray(descriptors, dtype=np.float32)
    if values.size and (values.min() < 0.0 or values.max() > 1.0):
        raise DataError(
            "descriptors must lie in [0, 1] (RootSIFT) to be stored as uint8; found "
            f"values in [{values.min():.3g}, {values.max():.3g}]"
        )
    return np.rint(values * np.float32(DESCRIPTOR_SCALE)).astype(np.uint8)


def dequantised(codes: np.ndarray) -> np.ndarray:
    """[N, D] uint8 codes back to float32 descriptors (code / 255)."""
    return np.asarray(codes).astype(np.float32) / np.float32(DESCRIPTOR_SCALE)


def on_descriptor_grid(features: LocalFeatures) -> LocalFeatures:
    """The same keypoints with descriptors rounded to the stored uint8 grid, so a map
    in memory matches exactly as it will after a save and a load."""
    return LocalFeatures(features.keypoints, dequantised(quantised(features.descriptors)))


def positions_of(poses: Sequence[Pose]) -> np.ndarray:
    """[M, 3] camera positions of camera-to-world poses."""
    if not poses:
        return np.zeros((0, 3))
    return np.stack([p.position for p in poses])


@dataclass(frozen=True, eq=False)
class StructureMap:
    """Local features and 3-D points of the map images, row i of each for image i.

    Attributes:
        features: per image, LocalFeatures (keypoints [N_i, 2] float32 pixel (x, y),
            descriptors [N_i, D] float32 RootSIFT).
        points: per image, [N_i, 3] float32 world points in metres, row k for
            keypoint k; NaN rows where the keypoint has no 3-D point.
        poses: per image, the camera-to-world Pose.
        cameras: per image, the PinholeCamera of its keypoints.
        names: per image, its name.
        source: "depth" (lifted with depth maps), "triangulated" (from matches
            between map images of known pose) or "colmap" (a COLMAP model's points,
            relocfw.structure.colmap_structure).
        skipped_views: the views that gave no 3-D point and why; their features are
            kept (a query may still match them, and the caller reports them).

    Everything is copied into read-only arrays and tuples when the map is made.
    Equality is identity (eq=False); compare maps with `same_as`.

    Raises:
        DataError: when the per-image sequences differ in length, a points array is
            not [N_i, 3] for its features, descriptor lengths differ between images,
            an entry has the wrong type, or `source` is not one of SOURCES.
    """

    features: tuple[LocalFeatures, ...]
    points: tuple[np.ndarray, ...]
    poses: tuple[Pose, ...]
    cameras: tuple[PinholeCamera, ...]
    names: tuple[str, ...]
    source: str
    skipped_views: tuple[SkippedView, ...] = ()

    def __post_init__(self) -> None:
        for field_name in ("features", "points", "poses", "cameras", "names", "skipped_views"):
            object.__setattr__(self, field_name, tuple(getattr(self, field_name)))
        count = len(self.features)
        for field_name in ("points", "poses", "cameras", "names"):
            if len(getattr(self, field_name)) != count:
                raise DataError(
                    f"structure map has {count} feature sets but "
                    f"{len(getattr(self, field_name))} {field_name}; one of each per image"
                )
        if self.source not in SOURCES:
            raise DataError(f"structure map source must be one of {SOURCES}, got {self.source!r}")
        dimensions = {f.descriptors.shape[1] for f in self.features if len(f)}
        if len(dimensions) > 1:
            raise DataError(
                f"structure map images have descriptors of lengths {sorted(dimensions)}; "
                "all must be one kind"
            )
        points = []
        for number, (features, pose, camera, name, rows) in enumerate(
            zip(self.features, self.poses, self.cameras, self.names, self.points, strict=True)
        ):
            if not isinstance(features, LocalFeatures):
                raise DataError(f"features[{number}] must be LocalFeatures")
            if not isinstance(pose, Pose):
                raise DataError(f"poses[{number}] must be a Pose")
            if not isinstance(camera, PinholeCamera):
                raise DataError(f"cameras[{number}] must be a PinholeCamera")
            if not isinstance(name, str):
                raise DataError(f"names[{number}] must be a string, got {name!r}")
            array = np.array(rows, dtype=np.float32)
            if array.shape != (len(features), 3):
                raise DataError(
                    f"points[{number}] ({name!r}) has shape {array.shape}, expected "
                    f"({len(features)}, 3): one row per keypoint"
                )
            array.setflags(write=False)
            points.append(array)
        object.__setattr__(self, "points", tuple(points))
        for skipped in self.skipped_views:
            if not isinstance(skipped, SkippedView):
                raise DataError("skipped_views must hold SkippedView values")

    def __len__(self) -> int:
        return len(self.features)

    def __repr__(self) -> str:
        # A summary: the default would print every array of every image.
        return (
            f"StructureMap({len(self)} images, {int(self.point_counts().sum())} points of "
            f"{sum(len(f) for f in self.features)} keypoints, source={self.source!r}, "
            f"{len(self.skipped_views)} skipped)"
        )

    @property
    def descriptor_dimensions(self) -> int:
        """D, the length of the map's descriptors (128 for an empty map)."""
        for features in self.features:
            if len(features):
                return int(features.descriptors.shape[1])
        return SIFT_DIMENSIONS

    def positions(self) -> np.ndarray:
        """[M, 3] float64 camera positions in metres."""
        return positions_of(self.poses)

    def optical_axes(self) -> np.ndarray:
        """[M, 3] float64 unit viewing directions (camera z axes) in the world."""
        return optical_axes(self.poses)

    def point_counts(self) -> np.ndarray:
        """[M] int64: how many keypoints of each image have a 3-D point."""
        return np.array([int(np.isfinite(p).all(axis=1).sum()) for p in self.points], np.int64)

    def same_as(self, other: StructureMap) -> bool:
        """Whether `other` holds exactly the same values (NaN rows equal NaN rows)."""
        if not isinstance(other, StructureMap) or len(self) != len(other):
            return False
        if (self.source, self.names, self.cameras, self.skipped_views) != (
            other.source,
            other.names,
            other.cameras,
            other.skipped_views,
        ):
            return False
        for a, b in zip(self.poses, other.poses, strict=True):
            if not (
                np.array_equal(a.position, b.position)
                and np.array_equal(a.quaternion, b.quaternion)
            ):
                return False
        for fa, fb, pa, pb in zip(
            self.features, other.features, self.points, other.points, strict=True
        ):
            if not (
                np.array_equal(fa.keypoints, fb.keypoints)
                and np.array_equal(fa.descriptors, fb.descriptors)
                and np.array_equal(pa, pb, equal_nan=True)
            ):
                return False
        return True

    # The builders, also reachable from the class (StructureMap.build_from_depth(...)).
    # Functions see module names, not class ones: these call the module's builders.
    @staticmethod
    def build_from_depth(*args: Any, **kwargs: Any) -> StructureMap:
        """`build_from_depth` of this module (same arguments)."""
        return build_from_depth(*args, **kwargs)

    @staticmethod
    def build_by_triangulation(*args: Any, **kwargs: Any) -> StructureMap:
        """`build_by_triangulation` of this module (same arguments)."""
        return build_by_triangulation(*args, **kwargs)

    def save(self, path: str | Path, key: str | None = None) -> None:
        """Write the map to one compressed npz file, all or nothing.

        Descriptors are stored as uint8 (round(255 x value)): exact for maps the
        builders made, whose descriptors are on that grid already.

        Args:
            path: the file to write (its folder is created); an existing file is
                replaced only when the new one is complete.
            key: the content key (`structure_key`) the map was built for, recorded in
                the file so `cached_structure_map` can tell a stale or copied file
                under that key's name; None records none.

        Raises:
            DataError: when a descriptor lies outside [0, 1] (not RootSIFT).
        """
        counts = np.array([len(f) for f in self.features], dtype=np.int64)
        dimensions = self.descriptor_dimensions
        keypoints = [f.keypoints for f in self.features]
        descriptors = [f.descriptors.reshape(-1, dimensions) for f in self.features]
        arrays = {
            "kind": np.array(FILE_KIND),
            "format": np.array(FORMAT_VERSION, dtype=np.int64),
            "source": np.array(self.source),
            "names": np.array(self.names, dtype=str).reshape(-1),
            "counts": counts,
            "keypoints": np.concatenate(keypoints) if keypoints else np.zeros((0, 2), np.float32),
            "descriptors": quantised(
                np.concatenate(descriptors) if descriptors else np.zeros((0, dimensions))
            ),
            "points": np.concatenate(self.points) if self.points else np.zeros((0, 3), np.float32),
            "positions": self.positions().reshape(-1, 3),
            "quaternions": np.array([p.quaternion for p in self.poses]).reshape(-1, 4),
            "cameras": np.array(
                [[c.fx, c.fy, c.cx, c.cy, c.width, c.height] for c in self.cameras],
                dtype=np.float64,
            ).reshape(-1, 6),
            "skipped_names": np.array([s.name for s in self.skipped_views], dtype=str),
            "skipped_reasons": np.array([s.reason for s in self.skipped_views], dtype=str),
        }
        if key is not None:
            arrays["key"] = np.array(str(key))
        with atomic_write(Path(path), "wb") as stream:
            np.savez_compressed(stream, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> StructureMap:
        """A map written by `save`.

        Args:
            path: the npz file.

        Returns:
            The StructureMap, equal (`same_as`) to the one saved.

        Raises:
            DataError: naming the file when it is missing, truncated, corrupt, not a
                relocfw structure map, of another format version, or inconsistent.
        """
        path = Path(path)
        return map_of_file_arrays(path, read_map_arrays(path))


def read_map_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of the npz file `path`, read in full; a DataError naming the file
    when it is missing, truncated, corrupt or not an npz file."""
    if not path.is_file():
        raise DataError(f"structure map not found: {path}")
    try:
        # allow_pickle=False: a map file can never run code when it is read.
        archive = np.load(path, allow_pickle=False)
    except Exception as error:  # zipfile, zlib and numpy raise many types
        raise DataError(
            f"cannot read structure map {path} (truncated or corrupt: {error})"
        ) from error
    if not hasattr(archive, "files"):
        raise DataError(f"{path} is not a relocfw structure map (an .npy array, not npz)")
    try:
        with archive:
            arrays = {name: archive[name] for name in archive.files}
    except Exception as error:  # a damaged member shows only when it is read
        raise DataError(
            f"cannot read structure map {path} (truncated or corrupt: {error})"
        ) from error
    return arrays


def map_of_file_arrays(path: Path, arrays: dict[str, np.ndarray]) -> StructureMap:
    """`map_of_arrays`, with any fault a DataError naming the file `path`."""
    try:
        return map_of_arrays(arrays)
    except (DataError, ConfigError, KeyError, ValueError, TypeError) as error:
        detail = f"missing array {error}" if isinstance(error, KeyError) else str(error)
        raise DataError(f"{path} is not a usable relocfw structure map: {detail}") from None


def recorded_key(arrays: dict[str, np.ndarray]) -> str | None:
    """The content key a map file records (`StructureMap.save`), None when it has none
    (written before files recorded their key)."""
    key = arrays.get("key")
    return str(key) if key is not None and key.shape == () else None


def map_of_arrays(arrays: dict[str, np.ndarray]) -> StructureMap:
    """The StructureMap of the arrays `StructureMap.save` writes; raises DataError,
    ConfigError, KeyError or ValueError on anything else (`load` names the file)."""
    kind = arrays.get("kind")
    if kind is None or kind.shape != () or str(kind) != FILE_KIND:
        raise DataError(f"not a {FILE_KIND} file")
    if int(arrays["format"]) != FORMAT_VERSION:
        raise DataError(
            f"format {int(arrays['format'])}; this relocfw reads format {FORMAT_VERSION} "
            "(delete the file to rebuild it)"
        )
    counts = arrays["counts"].astype(np.int64)
    names = [str(n) for n in arrays["names"]]
    count = len(counts)
    total = int(counts.sum())
    shapes = {
        "keypoints": (total, 2),
        "points": (total, 3),
        "positions": (count, 3),
        "quaternions": (count, 4),
        "cameras": (count, 6),
    }
    for name, shape in shapes.items():
        if arrays[name].shape != shape:
            raise DataError(f"{name} has shape {arrays[name].shape}, expected {shape}")
    if arrays["descriptors"].dtype != np.uint8 or arrays["descriptors"].shape[0] != total:
        raise DataError("descriptors must be uint8, one row per keypoint")
    if len(names) != count or (counts < 0).any():
        raise DataError("names and counts disagree")
    if not (np.isfinite(arrays["positions"]).all() and np.isfinite(arrays["quaternions"]).all()):
        raise DataError("a pose holds NaN or infinity")
    ends = np.cumsum(counts)
    starts = ends - counts
    descriptors = dequantised(arrays["descriptors"])
    features = [
        LocalFeatures(arrays["keypoints"][a:b], descriptors[a:b])
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True)
    ]
    points = [arrays["points"][a:b] for a, b in zip(starts.tolist(), ends.tolist(), strict=True)]
    poses = [Pose(p, q) for p, q in zip(arrays["positions"], arrays["quaternions"], strict=True)]
    cameras = [
        PinholeCamera(fx, fy, cx, cy, int(width), int(height))
        for fx, fy, cx, cy, width, height in arrays["cameras"].tolist()
    ]
    skipped = [
        SkippedView(str(n), str(r))
        for n, r in zip(arrays["skipped_names"], arrays["skipped_reasons"], strict=True)
    ]
    return StructureMap(
        features=tuple(features),
        points=tuple(points),
        poses=tuple(poses),
        cameras=tuple(cameras),
        names=tuple(names),
        source=str(arrays["source"]),
        skipped_views=tuple(skipped),
    )


def checked_views(views: Sequence[MapView]) -> None:
    """A DataError unless `views` is a non-empty sequence (its entries are checked one
    at a time as they are read, `checked_view`, so a lazy sequence loads each once)."""
    if isinstance(views, MapView | str | bytes) or not isinstance(views, Sequence):
        raise DataError(f"views must be a sequence of MapView, got {type(views).__name__}")
    if len(views) == 0:
        raise DataError("views is empty: a structure map needs at least one map image")


def checked_view(number: int, view: object) -> MapView:
    """`view` itself when it is a MapView with a finite pose, else a DataError naming it."""
    if not isinstance(view, MapView):
        raise DataError(f"views[{number}] must be a MapView, got {type(view).__name__}")
    if not view.pose.is_finite:
        raise DataError(f"map view {view.name!r}: pose holds NaN or infinity")
    return view


def depth_of_view(view: MapView) -> tuple[np.ndarray | None, str]:
    """The view's depth map in metres, in its image's pixels, or (None, why not).

    A view with a depth camera has its depth registered into the image first
    (relocfw.structure.registration.register_depth), so each keypoint reads the depth
    of its own surface point; without one, the map is read as registered already.

    Missing, unreadable and corrupt files are a reason to skip the view (one bad
    frame of a recording should not stop a map of thousands); a depth map whose
    size is not its depth camera's, or (without a depth camera) whose aspect ratio
    differs from the image's, or whose median depth is implausible in metres
    (relocfw.data.depth.check_depth_range: a wrong depth_units_per_metre), is a
    DataError, since every view of the map would be lifted wrongly.
    """
    if view.depth_path is None:
        return None, "no depth map (depth_path is None)"
    try:
        depth = read_depth(view.depth_path, None, view.depth_units_per_metre)
    except DataError as error:
        return None, str(error)
    # Raised, not skipped: a wrong scale is the dataset's, and every view has it.
    check_depth_range(depth, view.depth_path, view.depth_units_per_metre)
    depth_height, depth_width = depth.shape
    if view.depth_camera is not None:
        sensor = view.depth_camera
        if (depth_width, depth_height) != (sensor.width, sensor.height):
            raise DataError(
                f"{view.depth_path}: depth map is {depth_width}x{depth_height} but the depth "
                f"camera of {view.name!r} is {sensor.width}x{sensor.height}"
            )
        return register_depth(depth, sensor, view.camera, view.depth_to_colour), ""
    # The depth map's height if it were scaled to the image's width.
    scaled_height = depth_height * view.camera.width / depth_width
    if abs(scaled_height - view.camera.height) > ASPECT_TOLERANCE_PX:
        raise DataError(
            f"{view.depth_path}: depth map is {depth_width}x{depth_height} but its image "
            f"({view.name!r}) is {view.camera.width}x{view.camera.height}; a depth map of "
            "another size must have the image's aspect ratio (it is taken to cover the "
            "same field of view)"
        )
    return depth, ""


def build_from_depth(
    views: Sequence[MapView],
    max_features: int = 1024,
    quiet: bool = False,
    image_scale: float = 1.0,
) -> StructureMap:
    """The structure of RGB-D map images: RootSIFT keypoints lifted with their depth.

    Each view's depth map (relocfw.data.depth.read_depth, in the view's
    depth_units_per_metre) gives each keypoint the depth of its nearest depth pixel
    (relocfw.structure.lifting.lift_keypoints). A view with a depth camera has its
    depth registered into the image's pixels first (depth_of_view); without one, a
    depth map of another resolution than the image is scaled to it when the aspect
    ratios agree.

    Policy for views without usable depth: the view is kept with its features and
    all-NaN points (queries may still match it; those matches give no
    correspondence) and listed in `skipped_views` with the reason: no depth_path,
    a missing, corrupt or non-16-bit file (read_depth's message, naming it), no
    depth reading at any keypoint, or no keypoints at all.

    Each view is read once, in order, so `views` may be a lazy sequence that loads
    its images on access.

    Args:
        views: the map images (M of them), each with pose, camera and depth_path.
        max_features: the most keypoints per image (>= 1), strongest first.
        quiet: show no progress bar.
        image_scale: the share of each side SIFT runs at, in (0, 1]
            (features.extract_rootsift; keypoints stay in the image's pixels).

    Returns:
        StructureMap with source "depth"; descriptors on the stored uint8 grid.

    Raises:
        DataError: naming the view when an entry is not a MapView or its pose is not
            finite; naming the depth file when its aspect ratio is not the image's
            or its median depth is implausible in metres (a wrong depth scale).
        ConfigError: when `max_features` is not an integer >= 1.
    """
    checked_views(views)
    max_features = integer_at_least("max_features", max_features, 1)
    image_scale = checked_image_scale(image_scale)
    features, points, poses, cameras, names, skipped = [], [], [], [], [], []
    progress = Progress(len(views), "map structure from depth", quiet=quiet)
    for number in range(len(views)):
        view = checked_view(number, views[number])
        found = on_descriptor_grid(extract_rootsift(view.image, max_features, image_scale))
        depth, reason = depth_of_view(view)
        if depth is None:
            lifted = np.full((len(found), 3), np.nan, dtype=np.float32)
        else:
            lifted = lift_keypoints(found.keypoints, depth, view.camera, view.pose)
            if len(found) == 0:
                reason = "no keypoints (an image without texture)"
            elif not np.isfinite(lifted).all(axis=1).any():
                reason = f"no keypoint has a depth reading in {view.depth_path}"
        if reason:
            skipped.append(SkippedView(view.name, reason))
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
        source="depth",
        skipped_views=tuple(skipped),
    )


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


def features_of_views(
    views: Sequence[MapView], max_features: int, progress: Progress, image_scale: float = 1.0
) -> tuple[list[LocalFeatures], list[Pose], list[PinholeCamera], list[str]]:
    """Each view read once, in order: its RootSIFT features (on the stored grid, SIFT
    at `image_scale`), pose, camera and name; one progress step per view."""
    image_scale = checked_image_scale(image_scale)
    features, poses, cameras, names = [], [], [], []
    for number in range(len(views)):
        view = checked_view(number, views[number])
        found = extract_rootsift(view.image, max_features, image_scale)
        features.append(on_descriptor_grid(found))
        poses.append(view.pose)
        cameras.append(view.camera)
        names.append(view.name)
        progress.advance(suffix="features")
    return features, poses, cameras, names


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
    count = len(views)
    progress = Progress(count + 1, "map structure by tracks", quiet=quiet)
    features, poses, cameras, names = features_of_views(views, max_features, progress, image_scale)
    points, partners = build_track_points(features, poses, cameras, checked)
    progress.advance(suffix="tracks")
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


def build_by_triangulation(
    views: Sequence[MapView],
    max_features: int = 1024,
    method: str = "tracks",
    quiet: bool = False,
    image_scale: float = 1.0,
    **settings: Any,
) -> StructureMap:
    """The structure of RGB map images of known pose: multi-view tracks
    (`build_by_track_triangulation`, method "tracks") or the earlier two-view
    medians (`build_by_two_view_triangulation`, method "two_view"); `settings` go to
    the chosen builder.

    Raises:
        ConfigError: when `method` is not one of TRIANGULATION_METHODS, or a setting
            is not the chosen builder's (naming it).
    """
    if method == "tracks":
        return build_by_track_triangulation(
            views, max_features, quiet=quiet, image_scale=image_scale, **settings
        )
    if method == "two_view":
        allowed = set(inspect.signature(build_by_two_view_triangulation).parameters)
        for key in settings:
            if key not in allowed or key in ("views", "max_features", "quiet", "image_scale"):
                raise ConfigError(f"triangulation.{key} is not a setting of method two_view")
        return build_by_two_view_triangulation(
            views, max_features, quiet=quiet, image_scale=image_scale, **settings
        )
    choices = ", ".join(TRIANGULATION_METHODS)
    raise ConfigError(f"triangulation.method must be one of {choices}, got {method!r}")


def structure_key(
    names: Sequence[str],
    poses: Sequence[Pose],
    cameras: Sequence[PinholeCamera],
    settings: dict[str, Any],
    depth_sensors: Sequence[tuple[PinholeCamera | None, np.ndarray | None]] | None = None,
) -> str:
    """A content key of a structure map: what makes it, hashed.

    The names, every pose and camera value (exact floats), each view's depth camera
    and depth-to-colour transform where it has one (depth registered with them lifts
    to other points than depth read pixel for pixel), and the builder's settings
    (which builder and every parameter of its build) go into one sha256,
    with FORMAT_VERSION and the versions of OpenCV (its SIFT makes the features) and
    relocfw (its builders make the points). The image pixels and depth files are not
    read here: the caller puts their digests in `settings` (FeaturesRefiner does).

    Args:
        names: the M map images' names.
        poses: their M camera-to-world poses.
        cameras: their M cameras.
        settings: JSON-able settings (values that are not JSON become str).
        depth_sensors: per view, its (depth_camera, depth_to_colour) as MapView holds
            them, or None where no view has a depth camera (the key is then what it
            was before views had one, so maps of registered depth stay cached).

    Returns:
        16 hex digits.

    Raises:
        DataError: when the sequences differ in length.
        ConfigError: when `settings` is not a dict.
    """
    if not isinstance(settings, dict):
        raise ConfigError(f"settings must be a dict, got {type(settings).__name__}")
    if not (len(names) == len(poses) == len(cameras)):
        raise DataError(
            f"{len(names)} names, {len(poses)} poses and {len(cameras)} cameras; one of "
            "each per map image"
        )
    payload = {
        "kind": FILE_KIND,
        "format": FORMAT_VERSION,
        "names": [str(n) for n in names],
        # json writes floats with repr, which round-trips exactly.
        "poses": [[*p.position.tolist(), *p.quaternion.tolist()] for p in poses],
        "cameras": [[c.fx, c.fy, c.cx, c.cy, c.width, c.height] for c in cameras],
        "settings": settings,
        **depth_sensor_entry(names, depth_sensors),
        "opencv": cv2.__version__,
        "relocfw": VERSION,
    }
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def depth_sensor_entry(
    names: Sequence[str],
    depth_sensors: Sequence[tuple[PinholeCamera | None, np.ndarray | None]] | None,
) -> dict[str, list]:
    """structure_key's part for depth cameras: {} where no view has one, else
    {"depth_sensors": per view [camera values or None, 16 transform values or None]}."""
    if depth_sensors is None or all(camera is None for camera, _ in depth_sensors):
        return {}
    if len(depth_sensors) != len(names):
        raise DataError(f"{len(names)} names but {len(depth_sensors)} depth sensors")
    entries = []
    for camera, transform in depth_sensors:
        values = None if camera is None else [camera.fx, camera.fy, camera.cx, camera.cy]
        sizes = None if camera is None else [camera.width, camera.height]
        matrix = None if transform is None else np.asarray(transform, np.float64).ravel().tolist()
        entries.append([values, sizes, matrix])
    return {"depth_sensors": entries}


def cached_structure_map(
    cache_dir: str | Path, key: str, build: Callable[[], StructureMap], quiet: bool = False
) -> StructureMap:
    """The map of `key` from `cache_dir/structure/<key>.npz`, built and saved if absent.

    Args:
        cache_dir: the cache folder (relocfw's cache_dir; `~` is expanded).
        key: the map's content key (`structure_key`).
        build: makes the map when it is not cached; called at most once.
        quiet: print no line saying whether the map was built or reused.

    Returns:
        The StructureMap (the one just built, which equals what was saved).

    The file records its key (`StructureMap.save`); a file under the key's name
    that records another key or none (copied, or written by older code) is not
    used: the map is rebuilt over it, with one note line on stderr.

    Raises:
        ConfigError: when `key` is not 8-64 lowercase hex digits (it names a file).
        DataError: naming the cached file when it cannot be read (delete it to
            rebuild), or when `build` returns something other than a StructureMap.
    """
    if not isinstance(key, str) or not KEY_PATTERN.fullmatch(key):
        raise ConfigError(f"key must be 8-64 lowercase hex digits (structure_key), got {key!r}")
    path = Path(cache_dir).expanduser() / "structure" / f"{key}.npz"
    if path.is_file():
        try:
            arrays = read_map_arrays(path)
            stored = recorded_key(arrays)
            structure = map_of_file_arrays(path, arrays) if stored == key else None
        except DataError as error:
            raise DataError(f"{error}; delete it to rebuild the map") from None
        if structure is not None:
            if not quiet:
                print(f"map structure: reused {path}", file=sys.stderr)
            return structure
        # Printed even when quiet: a cache file that is not what its name says is
        # worth one line.
        print(
            f"note: map structure {path} records key {stored or 'none'}, not {key}: rebuilding it",
            file=sys.stderr,
        )
    structure = build()
    if not isinstance(structure, StructureMap):
        raise DataError(f"build must return a StructureMap, got {type(structure).__name__}")
    # A writer killed mid-file leaves a temporary; another run's live temporary is
    # locked and kept (relocfw.core.atomic_files).
    remove_stale_temporaries(path)
    structure.save(path, key)
    if not quiet:
        print(f"map structure: built and saved {path}", file=sys.stderr)
    return structure
