"""A structure map on disk, read image by image: for maps too large for memory.

A StructureMap holds every image's float32 descriptors in memory: about 400 KB per
Red Kitchen image at 1024 features, 40 GB for a building of 10^5 images, and its npz
file (about 76 KB per image) must be decompressed whole to be read. A query needs
only its ten or so keyframes. So the compact layout is a folder of flat, uncompressed
.npy arrays, opened memory-mapped (np.load(mmap_mode="r")): opening reads a few small
arrays, and each keyframe's rows come from the disk (or the page cache) when a query
asks for them.

The map's folder is a symbolic link to its current version, a hidden folder beside
it that a writer never changes once published (relocfw.structure.compact_writer);
`open` resolves the link once and reads every file from that version (a plain folder,
as an older relocfw wrote, is read as it is). Each version holds:

    map.json       kind, format, source, images M, rows T, the descriptor code and
                   point dtype, each array file's size in bytes and its SHA-256
                   ("sha256"; written last: a folder without it is not a map)
    offsets.npy    [M + 1] int64: image i's rows are offsets[i] .. offsets[i + 1]
    codes.npy      [T, B] uint8 descriptor codes (relocfw.structure.descriptor_codes:
                   B = 128 for the uint8 grid, B = S for a product quantiser)
    points.npy     [T, 3] float16 or float32: each row's 3-D point in its OWN image's
                   camera frame (x right, y down, z forward, metres)
    poses.npy      [M, 7] float64 camera-to-world (position, quaternion w first)
    cameras.npy    [M, 6] float64 (fx, fy, cx, cy, width, height)
    names.npy      [M] bytes, each name in UTF-8
    centres.npy    [S, 256, 128 / S] float32, product quantiser only

Why this shape:
- Only keypoints with a 3-D point are kept. The others give no correspondence; they
  took part in matching (a keyframe's second-nearest descriptor in Lowe's ratio
  test, relocfw.structure.map_state), so dropping them changes a few matches, by an
  accuracy cost the scale benchmark measures (benchmarks/structure_scale.py).
- No keypoint pixels: a query reads the map's 3-D points, never its pixels. A row's
  keypoint is given back as its point projected into its image, which for a point
  lifted from depth is the keypoint itself (to the points' rounding) and for a
  triangulated point lies within the builder's reprojection bound.
- Points in the camera frame: their size is the scene depth whatever the world's
  coordinates (a building's kilometres), so float16 keeps a relative precision of
  2^-11 (1.5 mm at 3 m, 0.3 px at f = 525); and a copy of an image under another
  pose keeps its points as they are.
- Flat arrays with offsets: one file per kind, whole images contiguous, so a
  keyframe is two small reads.

Measured on Red Kitchen (benchmarks/structure_scale.py: 400 training frames at 1024
features, 30 test queries, the same 10 keyframes each): the StructureMap in memory
gave a median 2.3 cm with 73% of queries within 5 cm / 5 deg; this layout with the
uint8 grid 2.3 cm, 73% (81.5 KB per image); with 16-byte product quantisation and
float16 points 2.3 cm, 77% (13.8 KB per image; 607 points an image).

Opening checks the small arrays fully (offsets, poses, cameras, names) and the large
ones by shape, dtype and size; reading 10^8 rows to check them would defeat the
layout, so each image's points are checked when the image is read. Any fault is one
DataError naming the file.

`CompactMap.of_arrays` gives the same map over arrays in memory (a model file's
tensors, relocfw.structure.compact_state) with the same checks, each fault naming
the array as the caller spells it; there the points are checked whole at once, as
they are already in memory.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from relocfw.core.camera import PinholeCamera, camera_fault
from relocfw.core.errors import DataError
from relocfw.core.geometry import quaternion_to_matrix
from relocfw.core.values import Pose
from relocfw.structure.descriptor_codes import PQ, DescriptorCodec
from relocfw.structure.features import LocalFeatures
from relocfw.structure.query_solver import StructureAnswer, checked_keyframes, localize_against
from relocfw.structure.structure_map import SOURCES, StructureMap

COMPACT_KIND = "relocfw compact structure map"
COMPACT_FORMAT = 1
META_FILE = "map.json"
POINT_DTYPES = ("float16", "float32")
# The array files of every map (a product quantiser's adds centres.npy).
ARRAY_FILES = ("offsets", "codes", "points", "poses", "cameras", "names")
QUATERNION_TOLERANCE = 1e-6
# map.json's record of each array file's SHA-256, written with the map; opening checks
# sizes only (reading 10^8 rows would defeat the layout), reuse checks these too
# (`content_faults`).
DIGESTS = "sha256"
DIGEST_BLOCK = 1 << 23
# How often `open` resolves the map's link again when the version it resolved was
# replaced while it read (each writer's publish takes milliseconds).
OPEN_ATTEMPTS = 5


class CompactMap:
    """A compact structure map, opened memory-mapped (`CompactMap.open`).

    Attributes:
        folder: the map's folder; None for a map over arrays in memory (`of_arrays`).
        source: how its points were made (StructureMap.source).
        codec: the descriptor code (relocfw.structure.descriptor_codes).
        offsets: [M + 1] int64, in memory.
        codes, points: the [T, B] and [T, 3] arrays, memory-mapped.
        poses, cameras: [M, 7] and [M, 6] float64, in memory.
        names: [M] UTF-8 bytes, in memory.
        label: what messages put before an array's name, for a map in memory
            (`of_arrays`: "<label>: <prefix>").
    """

    def __init__(
        self,
        folder: Path | None,
        source: str,
        codec: DescriptorCodec,
        arrays: dict,
        label: str = "compact map: ",
    ) -> None:
        self.folder = folder
        self.label = label
        self.source = source
        self.codec = codec
        self.offsets = arrays["offsets"]
        self.codes = arrays["codes"]
        self.points = arrays["points"]
        self.poses = arrays["poses"]
        self.cameras = arrays["cameras"]
        self.names = arrays["names"]
        # The folder the files were read from (`open`: the version its link named),
        # and their bytes on disk.
        self.version: Path | None = None
        self.stored_bytes = 0

    @classmethod
    def open(cls, folder: str | Path) -> CompactMap:
        """The map in `folder`, its large arrays memory-mapped.

        Raises:
            DataError: naming the file that is missing, truncated, of another kind,
                format or shape, or holds values a map cannot (offsets that do not
                rise from 0 to the rows, a pose that is not finite and unit, a
                camera that is not one).
        """
        # The folder is a link to the current version of the map (written by
        # relocfw.structure.compact_writer), or a plain folder: resolved once, so every
        # file comes from one version. A writer removes a version once another is
        # current; a reader that resolved it just before reads the current one.
        # Messages name the map's files as the caller names the map.
        folder = Path(folder)
        for _ in range(OPEN_ATTEMPTS - 1):
            version = Path(os.path.realpath(folder))
            try:
                return cls.open_version(version, folder)
            except DataError:
                if Path(os.path.realpath(folder)) == version:
                    raise
        return cls.open_version(Path(os.path.realpath(folder)), folder)

    @classmethod
    def open_version(cls, version: Path, folder: Path) -> CompactMap:
        """`open` of one resolved folder (a version of the map `folder`)."""
        meta = read_meta(version, folder)
        codec = DescriptorCodec(None)
        if meta["codes"] == PQ:
            codec = DescriptorCodec(np.array(load_array(version, "centres", meta, folder)))
        arrays = {name: load_array(version, name, meta, folder) for name in ARRAY_FILES}
        check_arrays(arrays, meta, codec, lambda name: str(folder / f"{name}.npy"))
        compact = cls(folder, meta["source"], codec, arrays)
        compact.version = version
        try:
            compact.stored_bytes = sum(p.stat().st_size for p in version.iterdir() if p.is_file())
        except OSError as error:  # removed meanwhile: `open` reads the current version
            raise DataError(f"cannot read {folder} ({error})") from None
        return compact

    @classmethod
    def of_arrays(
        cls,
        arrays: dict[str, np.ndarray],
        meta: dict,
        centres: np.ndarray | None = None,
        label: str = "compact map",
        prefix: str = "",
    ) -> CompactMap:
        """The map over arrays in memory: one per ARRAY_FILES name, as the files hold
        them, and `meta` as map.json holds it (without file_bytes: there are no files).

        Used where a map travels inside another file (a model file's tensors), so the
        arrays are data from anyone: every check `open` makes is made here, the points
        whole (they are in memory already, so the per-image check `open` defers costs
        nothing to do now).

        Args:
            arrays: offsets, codes, points, poses, cameras and names.
            meta: kind, format, source, images, rows, codes, code_bytes, point_dtype.
            centres: a product quantiser's centres (meta codes "pq"), else None.
            label: how messages name the arrays' owner.
            prefix: put before each array's name in messages ("<label>: <prefix><name>":
                the key the caller stores it under).

        Raises:
            DataError: naming the array (or meta key) that is missing or does not fit.
        """
        checked_meta(meta, f"{label}: {prefix}meta", needs_file_bytes=False)
        if (meta["codes"] == PQ) != (centres is not None):
            raise DataError(
                f"{label}: {prefix}centres must be given exactly when the codes are {PQ}"
            )
        try:
            codec = DescriptorCodec(None if centres is None else np.array(centres))
        except DataError as error:
            raise DataError(f"{label}: {prefix}centres: {error}") from None
        if codec.code_bytes != meta["code_bytes"]:
            raise DataError(
                f"{label}: {prefix}code_bytes is {meta['code_bytes']}, the codec's "
                f"{codec.code_bytes}"
            )
        missing = [name for name in ARRAY_FILES if not isinstance(arrays.get(name), np.ndarray)]
        if missing:
            raise DataError(f"{label}: {prefix}{missing[0]} must be an array")
        arrays = {name: arrays[name] for name in ARRAY_FILES}
        check_arrays(arrays, meta, codec, lambda name: f"{label}: {prefix}{name}")
        points = arrays["points"]
        if not (np.isfinite(points).all() and (points[:, 2] > 0).all()):
            raise DataError(
                f"{label}: {prefix}points hold values that are not finite or not in front "
                "of their camera"
            )
        return cls(None, meta["source"], codec, arrays, f"{label}: {prefix}")

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __repr__(self) -> str:
        where = self.folder if self.folder is not None else "in memory"
        return (
            f"CompactMap({where}, {len(self)} images, {len(self.codes)} points, "
            f"{self.codec.kind} {self.codec.code_bytes} B, {self.points.dtype})"
        )

    def checked(self, index: int) -> int:
        """`index` when it is an image of the map (numpy would read -1 as the last)."""
        if isinstance(index, bool) or not isinstance(index, int | np.integer):
            raise DataError(f"an image index must be an integer, got {index!r}")
        if not 0 <= index < len(self):
            raise DataError(f"image {index} is not in the map (0 .. {len(self) - 1})")
        return int(index)

    def rows(self, index: int) -> slice:
        """Image `index`'s rows of the flat arrays."""
        index = self.checked(index)
        return slice(int(self.offsets[index]), int(self.offsets[index + 1]))

    def name(self, index: int) -> str:
        return bytes(self.names[self.checked(index)]).decode("utf-8")

    def pose(self, index: int) -> Pose:
        row = self.poses[self.checked(index)]
        return Pose(row[:3], row[3:])

    def camera(self, index: int) -> PinholeCamera:
        fx, fy, cx, cy, width, height = self.cameras[self.checked(index)].tolist()
        return PinholeCamera(fx, fy, cx, cy, int(width), int(height))

    def camera_points(self, index: int) -> np.ndarray:
        """[N, 3] float32 points of image `index` in its camera frame, read from disk.

        Raises:
            DataError: naming points.npy when a point is not finite or not in front of
                the camera (a damaged file).
        """
        points = np.asarray(self.points[self.rows(index)], dtype=np.float32)
        if not (np.isfinite(points).all() and (points[:, 2] > 0).all()):
            raise DataError(
                f"{self.array_name('points')}: image {index} has points that are not "
                "finite or not in front of its camera (a damaged map)"
            )
        return points

    def array_name(self, name: str) -> str:
        """How a message names one of the map's arrays: its file, or (in memory) its
        label and name."""
        if self.folder is None:
            return f"{self.label}{name}"
        return str(self.folder / f"{name}.npy")

    def features(self, index: int) -> LocalFeatures:
        """Image `index`'s LocalFeatures: decoded descriptors, and its points projected
        into it as keypoints (see the module's note)."""
        return LocalFeatures(
            projected(self.camera_points(index), self.camera(index)),
            self.codec.decode(np.asarray(self.codes[self.rows(index)])),
        )

    def world_points(self, index: int) -> np.ndarray:
        """[N, 3] float32 world points of image `index`."""
        return in_world(self.camera_points(index), self.poses[self.checked(index)])

    def keyframe_map(self, keyframes: Sequence[int]) -> StructureMap:
        """A StructureMap of just these images, in this order (row k: keyframes[k]):
        what localize_against needs of a query's keyframes."""
        chosen = [self.checked(i) for i in keyframes]
        features, points = [], []
        for index in chosen:
            camera_points = self.camera_points(index)
            descriptors = self.codec.decode(np.asarray(self.codes[self.rows(index)]))
            keypoints = projected(camera_points, self.camera(index))
            features.append(LocalFeatures(keypoints, descriptors))
            points.append(in_world(camera_points, self.poses[index]))
        return StructureMap(
            features=tuple(features),
            points=tuple(points),
            poses=tuple(self.pose(i) for i in chosen),
            cameras=tuple(self.camera(i) for i in chosen),
            names=tuple(self.name(i) for i in chosen),
            source=self.source,
        )

    def file_bytes(self) -> int:
        """The map's size on disk: every file of the version opened, counted when it
        was opened (0 in memory), so a writer publishing another version meanwhile
        (and removing this one) changes nothing."""
        return self.stored_bytes

    def resident_bytes(self) -> int:
        """What opening holds in memory: the arrays read whole (not the mapped ones)."""
        arrays = (self.offsets, self.poses, self.cameras, self.names)
        centres = self.codec.centres
        return sum(a.nbytes for a in arrays) + (0 if centres is None else centres.nbytes)


def file_digest(path: Path) -> str:
    """The SHA-256 of a file's bytes, read in blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        while block := stream.read(DIGEST_BLOCK):
            digest.update(block)
    return digest.hexdigest()


def content_faults(compact: CompactMap) -> list[str]:
    """The array files of an opened map whose bytes are not those map.json records
    (rewritten at the same size, which `open`'s size check cannot see), or a note that
    it records none; empty when every file is as written. Reads every byte of the map:
    32 ms for a 400-image map of 607 points each (33 MB, in the page cache; about
    0.1 s per 100 MB, so 10 s or so for 10^5 images)."""
    if compact.version is None:
        return []
    meta = read_meta(compact.version, compact.folder)
    recorded = meta.get(DIGESTS)
    if not isinstance(recorded, dict):
        return [f"{compact.folder / META_FILE} records no {DIGESTS} of its files"]
    names = [name for name in meta["file_bytes"] if name in recorded]
    if sorted(names) != sorted(meta["file_bytes"]):
        return [f"{compact.folder / META_FILE} records no {DIGESTS} of some files"]
    faults = []
    for name in sorted(names):
        try:
            same = file_digest(compact.version / name) == recorded[name]
        except OSError:
            same = False
        if not same:
            faults.append(f"{compact.folder / name} is not the file written")
    return faults


def in_world(camera_points: np.ndarray, pose_row: np.ndarray) -> np.ndarray:
    """[N, 3] float32 world points of camera-frame points under a stored pose row
    (position, quaternion w first); computed in float64, so a world far from the
    origin loses nothing but the final rounding."""
    rotation = quaternion_to_matrix(pose_row[3:])
    return (camera_points.astype(np.float64) @ rotation.T + pose_row[:3]).astype(np.float32)


def projected(camera_points: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """[N, 2] float32 pixels of camera-frame points (z > 0)."""
    z = camera_points[:, 2].astype(np.float64)
    x = camera.fx * camera_points[:, 0] / z + camera.cx
    y = camera.fy * camera_points[:, 1] / z + camera.cy
    return np.stack([x, y], axis=1).astype(np.float32)


def localize_in_compact_map(
    compact: CompactMap,
    query_image: np.ndarray | None,
    camera: PinholeCamera,
    keyframes: Sequence[int],
    **options: object,
) -> StructureAnswer:
    """localize_against a compact map: the keyframes are read from disk into a small
    StructureMap first (repeats dropped, as localize_against drops them); `options`
    are localize_against's (max_features, ratio, ...)."""
    if not isinstance(compact, CompactMap):
        raise DataError(f"compact must be a CompactMap, got {type(compact).__name__}")
    chosen = checked_keyframes(keyframes, len(compact))
    return localize_against(
        compact.keyframe_map(chosen), query_image, camera, list(range(len(chosen))), **options
    )


def read_meta(folder: Path, shown: Path | None = None) -> dict:
    """map.json of `folder`, checked; DataError naming it in `shown` (the map's
    folder as the caller names it; default `folder`)."""
    path, named = folder / META_FILE, (shown or folder) / META_FILE
    if not path.is_file():
        raise DataError(f"not a relocfw compact structure map: {named} is missing")
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataError(f"cannot read {named} (truncated or corrupt: {error})") from None
    return checked_meta(meta, str(named))


def checked_meta(meta: object, where: str, needs_file_bytes: bool = True) -> dict:
    """`meta` (map.json's mapping) when every key holds what a map's can; DataError
    naming `where` and the key."""
    if not isinstance(meta, dict) or meta.get("kind") != COMPACT_KIND:
        raise DataError(f"{where} is not a {COMPACT_KIND} file")
    if meta.get("format") != COMPACT_FORMAT:
        raise DataError(
            f"{where}: format {meta.get('format')!r}; this relocfw reads format {COMPACT_FORMAT}"
        )
    wanted = {"source": SOURCES, "codes": ("grid", PQ), "point_dtype": POINT_DTYPES}
    for key, choices in wanted.items():
        if meta.get(key) not in choices:
            raise DataError(f"{where}: {key} must be one of {choices}, got {meta.get(key)!r}")
    for key in ("images", "rows", "code_bytes"):
        value = meta.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise DataError(f"{where}: {key} must be a whole number, got {value!r}")
    if needs_file_bytes and not isinstance(meta.get("file_bytes"), dict):
        raise DataError(f"{where}: file_bytes must map each array file to its size")
    return meta


def load_array(folder: Path, name: str, meta: dict, shown: Path | None = None) -> np.ndarray:
    """`name`.npy of the map, memory-mapped, after its size is checked against
    map.json's record (a truncated or overwritten file is named, not misread); messages
    name it in `shown` (default `folder`)."""
    path, named = folder / f"{name}.npy", (shown or folder) / f"{name}.npy"
    expected = meta["file_bytes"].get(f"{name}.npy")
    try:
        size = path.stat().st_size
    except OSError:
        raise DataError(f"compact structure map file missing: {named}") from None
    if size != expected:
        raise DataError(
            f"{named} is {size} bytes, map.json records {expected} (truncated or replaced)"
        )
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        raise DataError(f"cannot read {named} (corrupt: {error})") from None


def check_arrays(
    arrays: dict, meta: dict, codec: DescriptorCodec, where: Callable[[str], str]
) -> None:
    """Shapes and dtypes of every array, and the values of the small ones; a fault is
    a DataError naming the array as `where(name)` spells it (a file or a tensor)."""
    count, total = meta["images"], meta["rows"]
    shapes = {
        "offsets": ((count + 1,), np.dtype(np.int64)),
        "codes": ((total, codec.code_bytes), np.dtype(np.uint8)),
        "points": ((total, 3), np.dtype(meta["point_dtype"])),
        "poses": ((count, 7), np.dtype(np.float64)),
        "cameras": ((count, 6), np.dtype(np.float64)),
    }
    for name, (shape, dtype) in shapes.items():
        array = arrays[name]
        if array.shape != shape or array.dtype != dtype:
            raise DataError(
                f"{where(name)} holds {array.dtype} {list(array.shape)}, "
                f"expected {dtype} {list(shape)}"
            )
    names = arrays["names"]
    if names.shape != (count,) or names.dtype.kind != "S":
        raise DataError(f"{where('names')} must hold {count} byte strings")
    for number, name in enumerate(np.asarray(names).tolist()):
        try:
            name.decode("utf-8")
        except UnicodeDecodeError:
            raise DataError(f"{where('names')}: name {number} is not UTF-8 ({name!r})") from None
    offsets = np.array(arrays["offsets"])
    if count and (offsets[0] != 0 or offsets[-1] != total or (np.diff(offsets) < 0).any()):
        raise DataError(f"{where('offsets')}: offsets must rise from 0 to {total}")
    poses = np.array(arrays["poses"])
    norms = np.linalg.norm(poses[:, 3:], axis=1)
    if not np.isfinite(poses).all() or (np.abs(norms - 1) > QUATERNION_TOLERANCE).any():
        raise DataError(f"{where('poses')}: a pose is not finite or has no unit quaternion")
    cameras = np.array(arrays["cameras"])
    # Vectorised (a building has 10^5 cameras): PinholeCamera's own checks and a
    # plausible size, focal length and principal point (relocfw.core.camera), at once.
    fault = camera_fault(cameras)
    if fault is not None:
        number, why = fault
        raise DataError(
            f"{where('cameras')}: camera {number} is not a camera: {why} "
            f"(fx, fy, cx, cy, width, height = {cameras[number].tolist()})"
        )
    # The small arrays in memory from here on: mapped ones would read the disk per image.
    arrays.update(offsets=offsets, poses=poses, cameras=cameras, names=np.array(names))
