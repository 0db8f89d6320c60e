"""Writing a compact structure map (the layout is relocfw.structure.compact_map's).

`CompactMapWriter` streams: the caller gives each image's row count up front (the
.npy headers hold the full shapes), then adds images one at a time, and the writer
appends their rows to codes.npy and points.npy. A map of 10^5 images is never in
memory, and the writes go through the file, not a memory map, so the writing
process's resident memory stays what the small arrays take.

All or nothing, and safe with several writers and readers of one map: the files go
to a hidden staging folder beside the target, map.json last. When complete it is
renamed to a version folder (`.<name>.version-<random>`) and the target, a symbolic
link to the current version, is swapped to it by one rename: a reader resolves the
link once and reads one whole version (relocfw.structure.compact_map), never half of
one and half of another. Writers publish in turn (a lock file `.<name>.lock` beside
the map), but nothing relies on that lock, which does nothing where flock does
nothing (some network mounts) or is missing (Windows): a writer reads the version the
link names just before its swap and, after it, removes that one version only (no
writer swaps a link to a version already swapped in, so it is never current again);
any other version, and any `.<name>.link-*` a killed writer left, is removed only
when an hour old and not named by the link. So two writers of one map both succeed,
the last one's map stays, and the name never points at a removed version. A reader
that resolved a version just removed opens the current one (CompactMap.open retries).

An exception leaves the target as it was and nothing of the writer's, with one
exception: a map an older relocfw wrote as a plain folder is moved aside before the
link is swapped in (a rename cannot replace a folder by a link), so for that one
moment, or after a failure that cannot even move it back, the name holds nothing. A
kill leaves a staging folder, which the next writer of the map removes
(relocfw.core.atomic_files.remove_stale_folders). An existing compact map at the
target (a link, or a plain folder) is replaced; any other existing folder is
refused, never deleted.

Where symbolic links are refused (vfat, exFAT, SMB shares, Windows without the
right) the map is published as a plain folder, as older relocfw did: the existing
map moved aside, the staging folder renamed to the target, the old one removed. A
reader there may find no map for that instant, and two writers may race.

`save_compact_map` writes a StructureMap this way: the rows with a 3-D point, their
points moved into their image's camera frame, descriptors coded with the codec.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Sequence
from contextlib import suppress
from pathlib import Path
from typing import IO

import numpy as np

from relocfw.core.atomic_files import (
    file_lock,
    release_folder,
    remove_stale_folders,
    staging_folder,
)
from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import quaternion_to_matrix
from relocfw.core.values import Pose
from relocfw.structure.compact_map import (
    COMPACT_FORMAT,
    COMPACT_KIND,
    DIGESTS,
    META_FILE,
    POINT_DTYPES,
    file_digest,
)
from relocfw.structure.descriptor_codes import DescriptorCodec, grid_codec
from relocfw.structure.structure_map import SOURCES, StructureMap

# A version or link of a map older than this and not named by its link is a killed
# writer's or a race's leftover (see `abandoned`); an hour, as a live writer needs
# milliseconds between making one and swapping it in, and a leftover costs only disk.
ABANDONED_SECONDS = 3600.0


class CompactMapWriter:
    """Writes a compact map image by image; use it as a context manager.

    Args:
        folder: the map's folder (created; an existing compact map is replaced).
        counts: rows (points) of each image, in the order they will be added.
        codec: how descriptors are coded; `add` takes the codes.
        source: how the points were made (StructureMap.source).
        point_dtype: "float16" (6 bytes a point) or "float32" (12).

    Raises:
        ConfigError: naming `source`, `point_dtype` or `counts` when out of range, or
            when `folder` exists and is not a compact map.
    """

    def __init__(
        self,
        folder: str | Path,
        counts: Sequence[int] | np.ndarray,
        codec: DescriptorCodec,
        source: str = "depth",
        point_dtype: str = "float16",
    ) -> None:
        if source not in SOURCES:
            raise ConfigError(f"source must be one of {SOURCES}, got {source!r}")
        if point_dtype not in POINT_DTYPES:
            raise ConfigError(f"point_dtype must be one of {POINT_DTYPES}, got {point_dtype!r}")
        counts = np.asarray(counts)
        if counts.ndim != 1 or counts.dtype.kind not in "iu" or (counts < 0).any():
            raise ConfigError("counts must be one whole number of rows per image, each >= 0")
        self.folder = Path(folder)
        if self.folder.exists() and not (self.folder / META_FILE).is_file():
            raise ConfigError(f"{self.folder} exists and is not a compact structure map")
        self.folder.parent.mkdir(parents=True, exist_ok=True)
        self.counts = counts.astype(np.int64)
        self.codec = codec
        self.source = source
        self.point_dtype = np.dtype(point_dtype)
        remove_stale_folders(self.folder.parent, staging_prefix(self.folder))
        self.staging, self.staging_lock = staging_folder(
            self.folder.parent, staging_prefix(self.folder)
        )
        self.added = 0
        self.poses: list[np.ndarray] = []
        self.cameras: list[list[float]] = []
        self.names: list[bytes] = []
        total = int(self.counts.sum())
        self.streams = {
            "codes": started_array(self.staging / "codes.npy", np.uint8, (total, codec.code_bytes)),
            "points": started_array(self.staging / "points.npy", self.point_dtype, (total, 3)),
        }

    def __enter__(self) -> CompactMapWriter:
        return self

    def __exit__(self, kind: object, error: object, trace: object) -> None:
        if kind is not None:
            self.abort()
            return
        try:
            self.close()
        except BaseException:
            self.abort()  # a failed finish leaves no staging folder either
            raise

    def add(
        self,
        codes: np.ndarray,
        camera_points: np.ndarray,
        pose: Pose,
        camera: PinholeCamera,
        name: str,
    ) -> None:
        """The next image: its descriptor codes [N, B] uint8 and points [N, 3] in its
        camera frame (z > 0), N its count.

        Raises:
            DataError: naming the image when N is not its count, the codes are not
                the codec's, or a point is not finite or not in front of the camera
                (float16 ends at 65504; a point nearer than its smallest z in front
                is stored at that z).
        """
        if self.added >= len(self.counts):
            raise DataError(f"image {name!r}: all {len(self.counts)} images are written")
        count = int(self.counts[self.added])
        codes = np.asarray(codes)
        if codes.dtype != np.uint8 or codes.shape != (count, self.codec.code_bytes):
            raise DataError(
                f"image {name!r}: codes must be uint8 [{count}, {self.codec.code_bytes}], got "
                f"{codes.dtype} {list(codes.shape)}"
            )
        points = np.asarray(camera_points, dtype=np.float64)
        if points.shape != (count, 3):
            raise DataError(
                f"image {name!r}: points must be [{count}, 3], got {list(points.shape)}"
            )
        with np.errstate(over="ignore"):  # an overflow is the check below's to name
            stored = points.astype(self.point_dtype)
        # A point in front by less than half the dtype's smallest step (3e-8 in float16)
        # rounds to z = 0; it keeps the smallest z in front instead, within the same
        # rounding every other coordinate gets.
        underflow = (points[:, 2] > 0) & (stored[:, 2] <= 0)
        stored[underflow, 2] = np.finfo(self.point_dtype).smallest_subnormal
        if not (np.isfinite(stored).all() and (stored[:, 2] > 0).all()):
            raise DataError(
                f"image {name!r}: a point is not finite or not in front of the camera as "
                f"{self.point_dtype} (use point_dtype float32 for a scene of such extent)"
            )
        if not (isinstance(pose, Pose) and pose.is_finite and isinstance(camera, PinholeCamera)):
            raise DataError(f"image {name!r}: needs a finite Pose and a PinholeCamera")
        self.streams["codes"].write(np.ascontiguousarray(codes).tobytes())
        self.streams["points"].write(np.ascontiguousarray(stored).tobytes())
        self.poses.append(np.concatenate([pose.position, pose.quaternion]))
        self.cameras.append(
            [camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height]
        )
        self.names.append(str(name).encode("utf-8"))
        self.added += 1

    def close(self) -> None:
        """Finish the map: the small arrays, map.json, then the folder into place.

        Raises:
            DataError: when fewer images were added than `counts` has.
        """
        if self.added != len(self.counts):
            self.abort()
            raise DataError(f"{self.added} images added, counts has {len(self.counts)}")
        digests = {}
        for name, stream in self.streams.items():
            stream.flush()
            os.fsync(stream.fileno())
            stream.close()
            digests[f"{name}.npy"] = stream.digest.hexdigest()
        offsets = np.concatenate([[0], np.cumsum(self.counts)]).astype(np.int64)
        arrays = {
            "offsets": offsets,
            "poses": np.array(self.poses, dtype=np.float64).reshape(-1, 7),
            "cameras": np.array(self.cameras, dtype=np.float64).reshape(-1, 6),
            "names": np.array(self.names, dtype=bytes).reshape(-1),
        }
        if self.codec.centres is not None:
            arrays["centres"] = self.codec.centres
        for name, array in arrays.items():
            np.save(self.staging / f"{name}.npy", array, allow_pickle=False)
            digests[f"{name}.npy"] = file_digest(self.staging / f"{name}.npy")
        meta = {
            "kind": COMPACT_KIND,
            "format": COMPACT_FORMAT,
            "source": self.source,
            "images": len(self.counts),
            "rows": int(offsets[-1]),
            "codes": self.codec.kind,
            "code_bytes": self.codec.code_bytes,
            "point_dtype": self.point_dtype.name,
            "file_bytes": {p.name: p.stat().st_size for p in sorted(self.staging.glob("*.npy"))},
            DIGESTS: dict(sorted(digests.items())),
        }
        (self.staging / META_FILE).write_text(json.dumps(meta, indent=1) + "\n")
        self.publish()

    def publish(self) -> None:
        """Make the finished staging folder the map (see the module's note): renamed
        to a version, the target's link swapped to it, the versions it replaced
        removed after the lock is given back."""
        try:
            with file_lock(lock_file(self.folder)):
                unused = publish_staging(self.staging, self.folder)
        finally:
            self.release()
        remove_unused(unused)

    def abort(self) -> None:
        """Drop everything written (the target is left as it was)."""
        for stream in self.streams.values():
            stream.close()
        shutil.rmtree(self.staging, ignore_errors=True)
        self.release()

    def release(self) -> None:
        """Give back the staging folder's lock, once (its descriptor's number may be
        another file's after it is closed)."""
        release_folder(self.staging_lock)
        self.staging_lock = -1


def staging_prefix(folder: Path) -> str:
    """How the staging folders of the map `folder` are named (then a random part)."""
    return f".{folder.name}.staging-"


def version_prefix(folder: Path) -> str:
    """How the version folders of the map `folder` are named (then a random part)."""
    return f".{folder.name}.version-"


def link_prefix(folder: Path) -> str:
    """How a writer's new link to its version is named before it is swapped in."""
    return f".{folder.name}.link-"


def lock_file(folder: Path) -> Path:
    """The file the writers of the map `folder` lock to publish in turn."""
    return folder.parent / f".{folder.name}.lock"


def linked_version(folder: Path) -> Path | None:
    """The version the link `folder` names now, or None (no link, or a link to
    anything but a version of this map beside it: never ours to remove)."""
    try:
        target = os.readlink(folder)
    except (OSError, ValueError):
        return None
    if os.sep in target or (os.altsep and os.altsep in target):
        return None
    if not target.startswith(version_prefix(folder)):
        return None
    return folder.parent / target


def publish_staging(staging: Path, folder: Path) -> list[Path]:
    """Publish the finished `staging` as the map `folder` (see the module's note);
    the folders and links it replaced, for `remove_unused` once the lock is given
    back. On a failure before the swap nothing of this writer's is left and the map
    stays as it was (a plain-folder map being moved aside is put back)."""
    token = staging.name.rsplit("-", 1)[-1]
    version = folder.parent / f"{version_prefix(folder)}{token}"
    link = folder.parent / f"{link_prefix(folder)}{token}"
    try:
        # Relative: the map's folder may be moved or mounted elsewhere whole. Made
        # before the version exists (a link may dangle), so a file system that refuses
        # links (vfat, exFAT, SMB, Windows without the right) publishes a plain folder
        # before any version is made.
        os.symlink(version.name, link, target_is_directory=True)
    except (OSError, NotImplementedError):
        return publish_plain(staging, folder, token)
    aside = None
    try:
        # A fresh age, so no other writer's sweep (`abandoned`) takes it for a killed
        # writer's in the instant before the swap.
        os.utime(staging)
        os.replace(staging, version)
        # Read before the swap: the one version this writer replaces. A version named
        # by the link was swapped in already, so no writer swaps to it again and
        # removing it after the swap cannot leave the name on a removed version.
        previous = linked_version(folder)
        if folder.is_dir() and not folder.is_symlink():
            # A map an older relocfw wrote as a plain folder: moved aside first (a
            # rename cannot replace a folder by a link); its readers see the new map
            # or none, and a failed swap puts it back.
            aside = folder.parent / f"{version_prefix(folder)}{token}-older"
            os.replace(folder, aside)
            previous = aside
        os.replace(link, folder)
    except BaseException:
        if aside is not None:
            with suppress(OSError):
                os.replace(aside, folder)
        link.unlink(missing_ok=True)
        shutil.rmtree(version, ignore_errors=True)
        raise
    return [p for p in (previous,) if p is not None] + abandoned(folder)


def publish_plain(staging: Path, folder: Path, token: str) -> list[Path]:
    """Publish `staging` as `folder` itself where links are refused: the map there (a
    folder, or a link another system made) moved aside, the staging folder renamed
    into place; returns what was moved aside (and the version a link named)."""
    aside = None
    if os.path.lexists(folder):
        aside = folder.parent / f"{version_prefix(folder)}{token}-older"
        previous = linked_version(folder)
        os.replace(folder, aside)
    try:
        os.replace(staging, folder)
    except BaseException:
        if aside is not None:
            with suppress(OSError):
                os.replace(aside, folder)
        raise
    if aside is None:
        return []
    return [aside] + ([previous] if previous is not None else [])


def abandoned(folder: Path) -> list[Path]:
    """Versions and links of the map `folder` that a killed writer left, or that two
    writers racing without a working lock both replaced: those past
    ABANDONED_SECONDS and not named by the map's link now (a live writer renames its
    version and swaps it in within milliseconds)."""
    current = linked_version(folder)
    now = time.time()
    found = []
    for prefix in (version_prefix(folder), link_prefix(folder)):
        for path in folder.parent.glob(f"{prefix}*"):
            try:
                old = now - path.lstat().st_mtime > ABANDONED_SECONDS
            except OSError:  # removed meanwhile
                continue
            if old and path != current:
                found.append(path)
    return found


def remove_unused(paths: Sequence[Path]) -> None:
    """Remove versions (folders) and links no longer named; what is gone already is
    skipped (another writer removed it)."""
    for path in paths:
        if path.is_symlink():
            path.unlink(missing_ok=True)
        else:
            shutil.rmtree(path, ignore_errors=True)


class DigestedStream:
    """A file open for writing that digests every byte written to it (`digest`), so
    a large array's digest costs no second read."""

    def __init__(self, path: Path) -> None:
        self.stream: IO[bytes] = open(path, "wb")  # noqa: SIM115 (closed by the writer)
        self.digest = hashlib.sha256()

    def write(self, data: bytes) -> int:
        self.digest.update(data)
        return self.stream.write(data)

    def flush(self) -> None:
        self.stream.flush()

    def fileno(self) -> int:
        return self.stream.fileno()

    def close(self) -> None:
        self.stream.close()


def started_array(path: Path, dtype: np.dtype, shape: tuple[int, ...]) -> DigestedStream:
    """A file holding the .npy header of a C-ordered array of `shape`, open for its
    rows to be appended."""
    stream = DigestedStream(path)
    header = {
        "descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
        "fortran_order": False,
        "shape": shape,
    }
    np.lib.format.write_array_header_1_0(stream, header)
    return stream


def camera_frame(world_points: np.ndarray, pose: Pose) -> np.ndarray:
    """[N, 3] float64 world points in the camera frame of a camera-to-world pose."""
    rotation = quaternion_to_matrix(pose.quaternion)
    return (np.asarray(world_points, dtype=np.float64) - pose.position) @ rotation


def save_compact_map(
    structure: StructureMap,
    folder: str | Path,
    codec: DescriptorCodec | None = None,
    point_dtype: str = "float16",
) -> None:
    """Write a StructureMap as a compact map: each image's rows with a 3-D point.

    Args:
        structure: the map.
        folder: the compact map's folder.
        codec: the descriptor code (None: the uint8 grid, 128 bytes, exact).
        point_dtype: "float16" or "float32".

    Raises:
        DataError: naming the image whose points do not fit `point_dtype`.
    """
    codec = grid_codec() if codec is None else codec
    kept = [np.isfinite(points).all(axis=1) for points in structure.points]
    counts = [int(rows.sum()) for rows in kept]
    with CompactMapWriter(folder, counts, codec, structure.source, point_dtype) as writer:
        for index, rows in enumerate(kept):
            pose = structure.poses[index]
            writer.add(
                codec.encode(structure.features[index].descriptors[rows]),
                camera_frame(structure.points[index][rows], pose),
                pose,
                structure.cameras[index],
                structure.names[index],
            )
