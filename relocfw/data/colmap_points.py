"""COLMAP's 3-D points and each image's observations of them, text and binary.

relocfw.data.colmap_format reads where each image was taken; this module reads what
the model saw: points3D (the triangulated points) and the POINTS2D of images.*
(where each image observed which point), so a structure-based stage can use the
model's own tracks (relocfw.structure.colmap_structure).

Layouts (COLMAP's "Output Format" documentation; binary is little endian):
    points3D.txt  POINT3D_ID X Y Z R G B ERROR TRACK[] (IMAGE_ID POINT2D_IDX pairs)
    points3D.bin  uint64 count; per point uint64 id, float64 xyz[3], uint8 rgb[3],
                  float64 error, uint64 track length n, n x (uint32 image id,
                  uint32 point2D index)
    images.txt    the line after each image line: X Y POINT3D_ID triples, -1 where
                  the keypoint has no 3-D point
    images.bin    per image, after its name: uint64 n, n x (float64 x, float64 y,
                  uint64 point3D id), 2^64 - 1 where there is none

A model of 10^5 points and 10^3 images is read with numpy: one array per file, no
Python object per point. Any damage (a truncated or corrupt file, a NaN coordinate, a
POINT3D_ID an image names that points3D lacks) is one DataError naming the file and
the line or record: a model's points are used together, so there is nothing to skip.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocfw.core.errors import DataError
from relocfw.core.observations import PointObservations

COUNT = struct.Struct("<Q")
IMAGE_HEAD = struct.Struct("<I4d3dI")  # image id, qvec, tvec, camera id
# A points3D.bin record before its track: id, xyz, rgb, error, track length.
POINT_HEAD_BYTES = 8 + 24 + 3 + 8 + 8
TRACK_LENGTH_AT = 8 + 24 + 3 + 8
TRACK_ELEMENT_BYTES = 8  # uint32 image id, uint32 point2D index
POINT2D = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<u8")])
# COLMAP's kInvalidPoint3DId: the largest uint64 in binary files, -1 in text ones.
NO_POINT_BINARY = np.uint64(2**64 - 1)
# COLMAP measures pixels from the image's corner, relocfw from the top-left pixel's
# centre (relocfw.data.colmap_cameras.pinhole_of moves the principal point alike).
PIXEL_CENTRE_SHIFT = 0.5


@dataclass(frozen=True, eq=False)
class ModelPoints:
    """The 3-D points of a points3D file.

    Attributes:
        ids: [P] int64 POINT3D_IDs, increasing.
        xyz: [P, 3] float64 world coordinates, row i for ids[i].
        path: the file they were read from (for messages).
    """

    ids: np.ndarray
    xyz: np.ndarray
    path: Path

    def __len__(self) -> int:
        return len(self.ids)

    def lookup(self, wanted: np.ndarray, where: str) -> np.ndarray:
        """[N, 3] coordinates of the POINT3D_IDs `wanted`; a DataError naming `where`
        (the image that refers to them) and this file when one is not here."""
        wanted = np.asarray(wanted, dtype=np.int64)
        rows = np.searchsorted(self.ids, wanted)
        rows = np.minimum(rows, max(len(self.ids) - 1, 0))
        found = (self.ids[rows] == wanted) if len(self.ids) else np.zeros(len(wanted), bool)
        if not found.all():
            missing = wanted[~found]
            raise DataError(
                f"{where}: refers to POINT3D_ID {int(missing[0])}, which {self.path} does not "
                f"hold ({len(missing)} such observation(s)): the model's files do not belong "
                "together, or one is damaged"
            )
        return self.xyz[rows]


def model_points(ids: np.ndarray, xyz: np.ndarray, path: Path) -> ModelPoints:
    """ModelPoints sorted by id; a DataError naming `path` on a repeated id."""
    order = np.argsort(ids, kind="stable")
    ids, xyz = ids[order], xyz[order]
    repeated = np.flatnonzero(np.diff(ids) == 0)
    if len(repeated):
        raise DataError(f"{path}: POINT3D_ID {int(ids[repeated[0]])} appears more than once")
    ids.setflags(write=False)
    xyz.setflags(write=False)
    return ModelPoints(ids, xyz, Path(path))


# ---------------------------------------------------------------------------- text


def _lines(path: Path) -> list[str]:
    if not path.is_file():
        raise DataError(f"file not found: {path}")
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as error:
        raise DataError(f"{path}: not a text file ({error})") from None


def read_points3d_text(path: Path) -> ModelPoints:
    """The points of a points3D.txt (ids and coordinates; colours, errors and tracks
    are passed over: the images' POINTS2D say who sees what)."""
    path = Path(path)
    numbers, heads = [], []
    for number, raw in enumerate(_lines(path), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        # Split off only the head: a long track is most of a line.
        fields = line.split(None, 8)
        if len(fields) < 8:
            raise DataError(
                f"{path}:{number}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK[]', found "
                f"{len(fields)} values"
            )
        numbers.append(number)
        heads.append(fields[:4])
    if not heads:
        return model_points(np.zeros(0, np.int64), np.zeros((0, 3)), path)
    table = np.array(heads)
    try:
        ids = table[:, 0].astype(np.int64)
        xyz = table[:, 1:4].astype(np.float64)
    except ValueError:
        # Found again line by line, only on failure, to name the bad line.
        for number, head in zip(numbers, heads, strict=True):
            try:
                int(head[0])
                [float(v) for v in head[1:]]
            except ValueError as error:
                raise DataError(f"{path}:{number}: POINT3D_ID X Y Z: {error}") from None
        raise DataError(f"{path}: POINT3D_ID X Y Z: not numbers") from None
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"{path}:{numbers[row]}: point {int(ids[row])} has a NaN or infinite coordinate "
            f"{xyz[row].tolist()}"
        )
    return model_points(ids, xyz, path)


def read_observations_text(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """Per image NAME of an images.txt: its observed (x, y) [N, 2] in COLMAP's pixels,
    their POINT3D_IDs [N] and where they were read ("images.txt:13"); keypoints
    without a 3-D point (-1) are left out."""
    path = Path(path)
    lines = _lines(path)
    found: dict[str, tuple[np.ndarray, np.ndarray, str]] = {}
    number = 0
    while number < len(lines):
        line = lines[number].strip()
        number += 1
        if not line or line.startswith("#"):
            continue
        # As COLMAP reads it (and relocfw.data.colmap_format): the line after an
        # image line is its POINTS2D line.
        fields = line.split(None, 9)
        points_line = lines[number] if number < len(lines) else ""
        number += 1
        source = f"{path}:{number}"
        if len(fields) != 10:
            raise DataError(f"{path}:{number - 1}: not an image line ({len(fields)} values)")
        values = points_line.split()
        if len(values) % 3:
            raise DataError(
                f"{source}: POINTS2D holds {len(values)} values, not X Y POINT3D_ID triples"
            )
        table = np.array(values).reshape(-1, 3)
        try:
            xy = table[:, :2].astype(np.float64)
            ids = table[:, 2].astype(np.int64)
        except ValueError as error:
            raise DataError(f"{source}: POINTS2D: not a number ({error})") from None
        found[fields[9].strip()] = observed(xy, ids, ids != -1, source)
    return found


def observed(
    xy: np.ndarray, ids: np.ndarray, has_point: np.ndarray, source: str
) -> tuple[np.ndarray, np.ndarray, str]:
    """The rows with a 3-D point; a DataError naming `source` on a NaN pixel."""
    xy, ids = xy[has_point], ids[has_point].astype(np.int64)
    if not np.isfinite(xy).all():
        raise DataError(f"{source}: POINTS2D holds a NaN or infinite pixel")
    return xy, ids, source


# -------------------------------------------------------------------------- binary


def _bytes(path: Path) -> bytes:
    if not path.is_file():
        raise DataError(f"file not found: {path}")
    return path.read_bytes()


def truncated(path: Path, offset: int, size: int, what: str) -> DataError:
    return DataError(f"{path}: truncated or corrupt at byte {offset} of {size} (reading {what})")


def read_points3d_binary(path: Path) -> ModelPoints:
    """The points of a points3D.bin (ids and coordinates, as read_points3d_text)."""
    path = Path(path)
    data = _bytes(path)
    size = len(data)
    if size < COUNT.size:
        raise truncated(path, 0, size, "the number of points")
    (count,) = COUNT.unpack_from(data, 0)
    if count * POINT_HEAD_BYTES > size - COUNT.size:
        raise DataError(
            f"{path}: corrupt header: {count} points announced, but {size - COUNT.size} "
            "bytes cannot hold them"
        )
    # Records vary in length with their tracks, so only their starts are found one
    # by one (a track-length read each); the values are then gathered in bulk.
    starts = np.empty(count, dtype=np.int64)
    offset = COUNT.size
    track_length = struct.Struct("<Q")
    for index in range(count):
        if offset + POINT_HEAD_BYTES > size:
            raise truncated(path, offset, size, f"point {index + 1} of {count}")
        starts[index] = offset
        (length,) = track_length.unpack_from(data, offset + TRACK_LENGTH_AT)
        offset += POINT_HEAD_BYTES + TRACK_ELEMENT_BYTES * length
        if offset > size:
            raise truncated(path, starts[index], size, f"the track of point {index + 1} of {count}")
    if offset != size:
        raise DataError(
            f"{path}: corrupt: {size - offset} bytes left after the last of the points "
            f"(at byte {offset})"
        )
    raw = np.frombuffer(data, dtype=np.uint8)
    ids = gathered(raw, starts, 0, np.dtype("<u8"), 1)[:, 0].astype(np.int64)
    xyz = gathered(raw, starts, 8, np.dtype("<f8"), 3)
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"{path}: point {row + 1} of {count} (POINT3D_ID {int(ids[row])}) has a NaN or "
            f"infinite coordinate {xyz[row].tolist()}"
        )
    return model_points(ids, xyz, path)


def gathered(
    raw: np.ndarray, starts: np.ndarray, at: int, dtype: np.dtype, count: int
) -> np.ndarray:
    """[len(starts), count] values of `dtype` read at each start + `at` of `raw`."""
    columns = starts[:, None] + at + np.arange(count * dtype.itemsize)
    return np.ascontiguousarray(raw[columns]).view(dtype).reshape(len(starts), count)


def read_observations_binary(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """As read_observations_text, of an images.bin."""
    path = Path(path)
    data = _bytes(path)
    size = len(data)
    if size < COUNT.size:
        raise truncated(path, 0, size, "the number of images")
    (count,) = COUNT.unpack_from(data, 0)
    offset = COUNT.size
    found: dict[str, tuple[np.ndarray, np.ndarray, str]] = {}
    for index in range(count):
        what = f"image {index + 1} of {count}"
        if offset + IMAGE_HEAD.size > size:
            raise truncated(path, offset, size, what)
        image_id = IMAGE_HEAD.unpack_from(data, offset)[0]
        offset += IMAGE_HEAD.size
        end = data.find(b"\0", offset)
        if end < 0:
            raise truncated(path, offset, size, f"the name of {what}")
        try:
            name = data[offset:end].decode("utf-8")
        except UnicodeDecodeError:
            raise DataError(f"{path}: corrupt at byte {offset} (the name of {what})") from None
        offset = end + 1
        if offset + COUNT.size > size:
            raise truncated(path, offset, size, f"the point count of {what}")
        (points,) = COUNT.unpack_from(data, offset)
        offset += COUNT.size
        if points * POINT2D.itemsize > size - offset:
            raise truncated(path, offset, size, f"the {points} 2-D points of {what}")
        table = np.frombuffer(data, dtype=POINT2D, count=points, offset=offset)
        offset += points * POINT2D.itemsize
        xy = np.column_stack([table["x"], table["y"]]).astype(np.float64)
        source = f"{path}: {what} (IMAGE_ID {image_id})"
        found[name] = observed(xy, table["id"], table["id"] != NO_POINT_BINARY, source)
    if offset != size:
        raise DataError(
            f"{path}: corrupt: {size - offset} bytes left after the last of the images "
            f"(at byte {offset})"
        )
    return found


# ------------------------------------------------------------------------ together


def model_points_file(images_file: Path) -> Path:
    """The points3D file of the same format beside an images file (it may not exist)."""
    images_file = Path(images_file)
    return images_file.with_name(f"points3D{images_file.suffix}")


def read_model_points(path: Path) -> ModelPoints:
    """A points3D.bin or points3D.txt, by its suffix."""
    path = Path(path)
    return read_points3d_binary(path) if path.suffix == ".bin" else read_points3d_text(path)


def read_model_observations(images_file: Path) -> dict[str, PointObservations]:
    """Per image NAME of a sparse model, the 3-D points it observed and where.

    Args:
        images_file: the model's images.bin or images.txt; points3D of the same
            format is read beside it.

    Returns:
        PointObservations by image NAME, keypoints in relocfw's pixels (COLMAP's
        minus half a pixel); an image with no observed point has an empty one. An
        empty dict when the model has no 3-D point at all: no points3D file (a model
        of poses only, as hand-written ones often are) or an empty one.

    Raises:
        DataError: naming the file and line or record on any damage, or an image's
            POINT3D_ID that points3D does not hold.
    """
    images_file = Path(images_file)
    points_file = model_points_file(images_file)
    if not points_file.is_file():
        return {}
    points = read_model_points(points_file)
    if images_file.suffix == ".bin":
        observations = read_observations_binary(images_file)
    else:
        observations = read_observations_text(images_file)
    if len(points) == 0:
        return {}
    return {
        name: PointObservations(
            keypoints=xy - PIXEL_CENTRE_SHIFT,
            points=points.lookup(ids, source),
            track_ids=ids,
            source=source,
        )
        for name, (xy, ids, source) in observations.items()
    }
