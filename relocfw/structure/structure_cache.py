"""A structure map built once: its content key (`structure_key`) and the cache of
one npz file per key (`cached_structure_map`)."""

from __future__ import annotations

import hashlib
import json
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from relocfw.core.atomic_files import remove_stale_temporaries
from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.values import Pose
from relocfw.core.version import VERSION
from relocfw.structure.structure_map import (
    FILE_KIND,
    FORMAT_VERSION,
    StructureMap,
    map_of_file_arrays,
    read_map_arrays,
    recorded_key,
)

# A key names a file under the cache folder: hex digits only, so it cannot name a path.
KEY_PATTERN = re.compile(r"[0-9a-f]{8,64}")


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
