"""The map's structure: each map image's local features and a 3-D point per keypoint.

Structure-based relocalization (as hloc does it) matches a query's local features
against a few map images and solves the query's pose from the 2-D/3-D
correspondences; this module holds what it matches against, the `StructureMap` value,
and its file format (one compressed npz file, `StructureMap.save` /
`StructureMap.load`). One builder per 3-D source, each its own module:

- `relocfw.structure.depth_structure.build_from_depth`: each keypoint lifted to 3-D
  with the image's depth map (RGB-D maps such as 7-Scenes);
- `relocfw.structure.triangulated_structure.build_by_triangulation`: RGB only; by
  default each keypoint's point is its multi-view track's, triangulated over every
  map image that sees it with the known poses held fixed (`track_structure`); the
  earlier two-view medians stay available (`two_view_structure`, method "two_view")
  for comparisons;
- `relocfw.structure.colmap_structure.build_from_colmap_points`: a COLMAP model's own
  3-D points (source "colmap").

`relocfw.structure.structure_cache` keys a map by what makes it and keeps one file per
key, so a map is built once.

Descriptors are kept quantised: RootSIFT components lie in [0, 1] and are stored as
round(255 x value) in uint8, a quarter of float32's space. The builders put the
descriptors on that grid when they make the map, so the map in memory is exactly the
map on disk (a map saved and loaded gives the same matches, bit for bit). Measured on
20 pairs of Red Kitchen training frames five apart (benchmarks/structure_query.py
--check-quantisation), 0.28% of the 6069 float32 mutual ratio-test matches were lost
and 0.13% new ones appeared: matches near the ratio bound.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocfw.core.atomic_files import atomic_write
from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.values import Pose
from relocfw.structure.covisibility import optical_axes
from relocfw.structure.features import (
    SIFT_DIMENSIONS,
    LocalFeatures,
)

# Bump when the file layout changes: it is part of every structure_key, so a cached
# map written by older code is never picked up by code that reads it differently.
FORMAT_VERSION = 1
FILE_KIND = "relocfw structure map"
SOURCES = ("depth", "triangulated", "colmap")
# RootSIFT components are in [0, 1]; uint8 steps of 1/255 (an error of at most 0.002
# per component, against nearest-neighbour distances of 0.3 and more).
DESCRIPTOR_SCALE = 255.0


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

    def save(self, path: str | Path, key: str | None = None) -> None:
        """Write the map to one compressed npz file, all or nothing.

        Descriptors are stored as uint8 (round(255 x value)): exact for maps the
        builders made, whose descriptors are on that grid already.

        Args:
            path: the file to write (its folder is created); an existing file is
                replaced only when the new one is complete.
            key: the content key (relocfw.structure.structure_cache.structure_key) the
                map was built for, recorded in the file so `cached_structure_map` can
                tell a stale or copied file under that key's name; None records none.

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
