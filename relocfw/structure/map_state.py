"""A StructureMap as a few flat tensors, and back: what a model file stores of it.

A model file (relocfw.model.model_file) is read by torch's weights-only loader, so a
map travels as plain tensors: every image's rows concatenated, with `offsets` saying
where each image's rows begin, rather than thousands of small tensors. What is kept
is what a query uses, and nothing else:

- `descriptors` [K, 128] uint8 of EVERY keypoint (the grid the builders put them on,
  relocfw.structure.structure_map.quantised). Keypoints without a 3-D point give no
  correspondence, but they do take part in matching: a query descriptor's nearest
  and second-nearest neighbours in a keyframe (Lowe's ratio test) and the mutual
  check are taken over all of the keyframe's keypoints. Dropping them changes which
  matches pass, so the answers would not be the run's.
- `keypoints` [K, 2] float32 pixels of every keypoint. A query never reads them (a
  correspondence is the query's pixel and the map's 3-D point); they cost 8 of the
  about 140 bytes a keypoint takes and keep the loaded map a whole StructureMap
  (`same_as` the built one where every 3-D point is a whole row).
- `points` [P, 3] float32 world points of only the keypoints that have one, and
  `point_keypoints` [P] int64: the keypoint row (of the concatenation) each belongs to,
  strictly increasing. A map from depth has a point for most keypoints; a
  triangulated one for fewer.
- `poses` [M, 7] float64 (position, quaternion w first) and `cameras` [M, 6]
  float64 (fx, fy, cx, cy, width, height).

Names and skipped views are not kept (a query reads neither): a loaded map names its
images "map image i". `map_of_state` checks every shape, dtype and value before
anything is built from it (a model file is data from anyone), each fault one
DataError naming the tensor.
"""

from __future__ import annotations

import numpy as np
import torch

from relocfw.core.camera import PinholeCamera, camera_fault
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.values import Pose
from relocfw.structure.features import SIFT_DIMENSIONS, LocalFeatures
from relocfw.structure.structure_map import SOURCES, StructureMap, dequantised, quantised

# The tensors of a map's state, and their dtypes.
MAP_TENSORS = {
    "offsets": torch.int64,
    "keypoints": torch.float32,
    "descriptors": torch.uint8,
    "point_keypoints": torch.int64,
    "points": torch.float32,
    "poses": torch.float64,
    "cameras": torch.float64,
    "source": torch.int64,
}
# How far a stored quaternion's norm may be from 1 (poses are written as unit ones).
QUATERNION_TOLERANCE = 1e-6


def map_state(structure: StructureMap) -> dict[str, torch.Tensor]:
    """The map as the flat tensors the module's note lists (a copy of its arrays)."""
    counts = np.array([len(f) for f in structure.features], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    dimensions = structure.descriptor_dimensions
    keypoints = np.concatenate(
        [f.keypoints for f in structure.features] + [np.zeros((0, 2), np.float32)]
    )
    descriptors = np.concatenate(
        [f.descriptors.reshape(-1, dimensions) for f in structure.features]
        + [np.zeros((0, dimensions), np.float32)]
    )
    points = np.concatenate(list(structure.points) + [np.zeros((0, 3), np.float32)])
    # A row is a point only when all three values are finite, as a query reads it
    # (relocfw.structure.query_solver.correspondences_of).
    has_point = np.isfinite(points).all(axis=1)
    poses = np.array([[*p.position, *p.quaternion] for p in structure.poses], np.float64)
    cameras = np.array(
        [[c.fx, c.fy, c.cx, c.cy, c.width, c.height] for c in structure.cameras], np.float64
    )
    return {
        "offsets": torch.from_numpy(offsets),
        "keypoints": torch.from_numpy(keypoints.astype(np.float32)),
        "descriptors": torch.from_numpy(quantised(descriptors)),
        "point_keypoints": torch.from_numpy(np.flatnonzero(has_point).astype(np.int64)),
        "points": torch.from_numpy(points[has_point].astype(np.float32)),
        "poses": torch.from_numpy(poses.reshape(-1, 7)),
        "cameras": torch.from_numpy(cameras.reshape(-1, 6)),
        "source": torch.tensor(SOURCES.index(structure.source), dtype=torch.int64),
    }


def map_of_state(state: dict[str, torch.Tensor], label: str = "map state") -> StructureMap:
    """The StructureMap `map_state` stored, every tensor checked first.

    Args:
        state: a mapping holding at least the MAP_TENSORS (others are ignored).
        label: how messages name the state (e.g. "refine=features state").

    Raises:
        DataError: naming the tensor that is missing, of another dtype or shape, holds
            NaN or infinity, or whose offsets or point indices do not fit the rest.
    """
    arrays = {key: checked_tensor(state, key, dtype, label) for key, dtype in MAP_TENSORS.items()}
    offsets, descriptors = arrays["offsets"], arrays["descriptors"]
    if offsets.ndim != 1 or len(offsets) < 2:
        raise DataError(
            f"{label}: offsets must be [M + 1] (M >= 1 map images), got {shape(offsets)}"
        )
    total = len(descriptors)
    if descriptors.ndim != 2 or descriptors.shape[1] != SIFT_DIMENSIONS:
        raise DataError(
            f"{label}: descriptors must be [K, {SIFT_DIMENSIONS}] (RootSIFT), got "
            f"{shape(descriptors)}"
        )
    if offsets[0] != 0 or offsets[-1] != total or (np.diff(offsets) < 0).any():
        raise DataError(
            f"{label}: offsets must rise from 0 to the {total} keypoints (one descriptor "
            f"row each), got {offsets.tolist()[:3]} .. {offsets[-1]}"
        )
    count = len(offsets) - 1
    expected = {
        "keypoints": (total, 2),
        "poses": (count, 7),
        "cameras": (count, 6),
        "source": (),
    }
    for key, wanted in expected.items():
        if arrays[key].shape != wanted:
            raise DataError(
                f"{label}: {key} must have shape {list(wanted)}, got {shape(arrays[key])}"
            )
    for key in ("keypoints", "points", "poses", "cameras"):
        if not np.isfinite(arrays[key]).all():
            raise DataError(f"{label}: {key} hold NaN or infinite values")
    indices, points = arrays["point_keypoints"], arrays["points"]
    if indices.ndim != 1 or points.shape != (len(indices), 3):
        raise DataError(
            f"{label}: points must be [P, 3] for the {shape(indices)} point_keypoints, "
            f"got {shape(points)}"
        )
    if len(indices) and (indices[0] < 0 or indices[-1] >= total or (np.diff(indices) <= 0).any()):
        raise DataError(
            f"{label}: point_keypoints must be strictly increasing keypoint rows in "
            f"[0, {total}), got {indices.min()} .. {indices.max()}"
        )
    source = int(arrays["source"])
    if not 0 <= source < len(SOURCES):
        known = ", ".join(f"{number} ({name})" for number, name in enumerate(SOURCES))
        raise DataError(f"{label}: source must be one of {known}, got {source}")
    return built_map(arrays, SOURCES[source], label)


def built_map(arrays: dict[str, np.ndarray], source: str, label: str) -> StructureMap:
    """The StructureMap of checked arrays (map_of_state's)."""
    offsets = arrays["offsets"]
    points = np.full((len(arrays["descriptors"]), 3), np.nan, dtype=np.float32)
    points[arrays["point_keypoints"]] = arrays["points"]
    descriptors = dequantised(arrays["descriptors"])
    spans = list(zip(offsets[:-1].tolist(), offsets[1:].tolist(), strict=True))
    features = [LocalFeatures(arrays["keypoints"][a:b], descriptors[a:b]) for a, b in spans]
    poses = []
    for number, row in enumerate(arrays["poses"]):
        if abs(float(np.linalg.norm(row[3:])) - 1.0) > QUATERNION_TOLERANCE:
            raise DataError(f"{label}: poses[{number}] has no unit quaternion")
        poses.append(Pose(row[:3], row[3:]))
    return StructureMap(
        features=tuple(features),
        points=tuple(points[a:b] for a, b in spans),
        poses=tuple(poses),
        cameras=tuple(
            camera_of_row(row, number, label) for number, row in enumerate(arrays["cameras"])
        ),
        names=tuple(f"map image {number}" for number in range(len(spans))),
        source=source,
    )


def camera_of_row(row: np.ndarray, number: int, label: str) -> PinholeCamera:
    """The PinholeCamera of a stored (fx, fy, cx, cy, width, height) row."""
    fx, fy, cx, cy, width, height = row.tolist()
    if not (width == int(width) and height == int(height)):
        raise DataError(f"{label}: cameras[{number}] has a size of {width} x {height} pixels")
    fault = camera_fault(row)
    if fault is not None:
        raise DataError(f"{label}: cameras[{number}]: {fault[1]}")
    try:
        return PinholeCamera(fx, fy, cx, cy, int(width), int(height))
    except ConfigError as error:
        raise DataError(f"{label}: cameras[{number}]: {error}") from None


def checked_tensor(state: object, key: str, dtype: torch.dtype, label: str) -> np.ndarray:
    """state[key] as a numpy array when it is a tensor of `dtype`, else a DataError
    naming the key (the dtype too: a float where indices belong is not converted)."""
    value = state.get(key) if isinstance(state, dict) else None
    if not isinstance(value, torch.Tensor):
        found = "nothing" if value is None else type(value).__name__
        raise DataError(f"{label}: {key} must be a tensor, got {found}")
    if value.dtype != dtype:
        raise DataError(f"{label}: {key} must be {dtype}, got {value.dtype}")
    return value.detach().cpu().numpy()


def shape(array: np.ndarray) -> list[int]:
    return list(array.shape)
