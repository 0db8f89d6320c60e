"""Reading depth maps: 16-bit PNGs in millimetres, as 7-Scenes stores them."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from relocfw.core.errors import ConfigError, DataError

# Kinect depth with no reading: 0 in the redistributed 7-Scenes copies, 65535 in the
# original archive. Neither is a distance (65.535 m is far beyond the sensor's range).
NO_READING = (0, 65535)
MILLIMETRES_PER_METRE = 1000.0

COLOUR_NAME = re.compile(r"^(?P<stem>.+)\.color\.(?:png|jpg|jpeg)$", re.IGNORECASE)


def positive_int(value: object) -> bool:
    """Whether `value` is an integer pixel count above zero (a bool is not one)."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool) and value > 0


def read_depth(path: str | Path, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """A depth map in metres from a 16-bit PNG in millimetres.

    Args:
        path: the PNG (7-Scenes: `frame-NNNNNN.depth.png`).
        expected_size: (width, height) the map must have (7-Scenes: (640, 480)); None
            accepts any size.

    Returns:
        [H, W] float32 depth along the camera's z axis in metres; NaN where the sensor
        had no reading (stored 0 or 65535), so a missing depth can never be used as a
        distance by mistake.

    Raises:
        DataError: naming the file when it is missing, cannot be decoded, is not a
            single-channel 16-bit image (naming the type found), or its size is not
            `expected_size` (naming both).
        ConfigError: when `expected_size` is not two positive integers.
    """
    if expected_size is not None:
        # Checked before the file, so a wrong call fails the same whatever the file.
        pair = isinstance(expected_size, tuple | list) and len(expected_size) == 2
        if not pair or not all(positive_int(v) for v in expected_size):
            raise ConfigError(
                f"expected_size must be (width, height) in pixels, got {expected_size!r}"
            )
    path = Path(path)
    if not path.is_file():
        raise DataError(f"depth map not found: {path}")
    # np.fromfile + imdecode rather than imread: imread returns None for a path with
    # non-ASCII characters on some platforms, indistinguishable from a corrupt file.
    data = np.fromfile(path, dtype=np.uint8)
    raw = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if raw is None:
        raise DataError(f"cannot decode depth map (corrupt or not an image): {path}")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        channels = 1 if raw.ndim == 2 else raw.shape[2]
        raise DataError(
            f"{path}: expected a single-channel 16-bit depth PNG (millimetres), found "
            f"{channels} channel(s) of {raw.dtype}"
        )
    if expected_size is not None:
        width, height = expected_size
        if raw.shape != (height, width):
            raise DataError(
                f"{path}: depth map is {raw.shape[1]}x{raw.shape[0]}, expected {width}x{height}"
            )
    depth = raw.astype(np.float32) / np.float32(MILLIMETRES_PER_METRE)
    depth[np.isin(raw, NO_READING)] = np.nan
    return depth


def depth_path_of(image_path: str | Path) -> Path:
    """The depth map beside a 7-Scenes colour image.

    Args:
        image_path: `.../frame-000000.color.jpg` (or `.color.png`).

    Returns:
        `.../frame-000000.depth.png` in the same folder (not checked to exist:
        `read_depth` names it if it is missing).

    Raises:
        DataError: naming the path when it does not follow 7-Scenes' naming.
    """
    image_path = Path(image_path)
    match = COLOUR_NAME.match(image_path.name)
    if match is None:
        raise DataError(
            f"{image_path}: not a 7-Scenes colour image name (frame-NNNNNN.color.jpg or "
            ".color.png), so its depth map cannot be found"
        )
    return image_path.with_name(f"{match.group('stem')}.depth.png")
