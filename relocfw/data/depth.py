"""Reading depth maps: 16-bit PNGs of z in fixed units (7-Scenes: millimetres; TUM: 1/5000 m)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np

from relocfw.core.errors import ConfigError, DataError
from relocfw.data.frames import Frame

# Kinect depth with no reading: 0 in the redistributed 7-Scenes copies, 65535 in the
# original archive. Neither is a distance (65.535 m is far beyond the sensor's range).
NO_READING = (0, 65535)
MILLIMETRES_PER_METRE = 1000.0
TUM_UNITS_PER_METRE = 5000.0  # TUM RGB-D's depth PNGs: 5000 units per metre
# Where the median valid depth of a real scene's depth map lies, in metres: far
# wider than any RGB-D sensor reads (Kinect: about 0.4-8 m), so only a wrong scale
# (a factor of 1000 or so) falls outside.
PLAUSIBLE_MEDIAN_DEPTH_M = (0.05, 100.0)

COLOUR_NAME = re.compile(r"^(?P<stem>.+)\.color\.(?:png|jpg|jpeg)$", re.IGNORECASE)


def positive_int(value: object) -> bool:
    """Whether `value` is an integer pixel count above zero (a bool is not one)."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool) and value > 0


def read_depth(
    path: str | Path,
    expected_size: tuple[int, int] | None = None,
    units_per_metre: float = MILLIMETRES_PER_METRE,
) -> np.ndarray:
    """A depth map in metres from a 16-bit PNG.

    Args:
        path: the PNG (7-Scenes: `frame-NNNNNN.depth.png`).
        expected_size: (width, height) the map must have (7-Scenes: (640, 480)); None
            accepts any size.
        units_per_metre: what one metre is stored as: 1000 (millimetres, 7-Scenes and
            the synthetic scene), 5000 (TUM RGB-D).

    Returns:
        [H, W] float32 depth along the camera's z axis in metres; NaN where the sensor
        had no reading (stored 0 or 65535), so a missing depth can never be used as a
        distance by mistake.

    Raises:
        DataError: naming the file when it is missing, cannot be decoded, is not a
            single-channel 16-bit image (naming the type found), or its size is not
            `expected_size` (naming both).
        ConfigError: when `expected_size` is not two positive integers, or
            `units_per_metre` is not a positive finite number.
    """
    scale = positive_scale(units_per_metre)
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
            f"{path}: expected a single-channel 16-bit depth PNG, found "
            f"{channels} channel(s) of {raw.dtype}"
        )
    if expected_size is not None:
        width, height = expected_size
        if raw.shape != (height, width):
            raise DataError(
                f"{path}: depth map is {raw.shape[1]}x{raw.shape[0]}, expected {width}x{height}"
            )
    depth = raw.astype(np.float32) / np.float32(scale)
    depth[np.isin(raw, NO_READING)] = np.nan
    return depth


def median_depth(depth: np.ndarray) -> float | None:
    """The median of a depth map's valid readings (finite, > 0) in metres; None
    without any."""
    values = np.asarray(depth, dtype=np.float64)
    valid = values[np.isfinite(values) & (values > 0)]
    return float(np.median(valid)) if valid.size else None


def check_depth_range(
    depth: np.ndarray, path: str | Path, units_per_metre: float = MILLIMETRES_PER_METRE
) -> None:
    """A DataError naming `path` when its depth, in metres, is not of a real scene.

    A depth map read with the wrong scale (millimetres taken as metres, TUM's 1/5000 m
    as millimetres off by far more) gives points that are silently wrong by that
    factor. The median of the valid readings must lie in PLAUSIBLE_MEDIAN_DEPTH_M,
    far wider than any RGB-D sensor's range, so only a wrong scale trips it.

    Args:
        depth: [H, W] depth in metres as read_depth gives it (NaN: no reading).
        path: the file it was read from (named in the error).
        units_per_metre: the scale it was read with (named in the error).

    Raises:
        DataError: naming the file, the median depth and the scale.
    """
    median = median_depth(depth)
    if median is None:
        return  # no reading at all: the builders report that view as skipped
    low, high = PLAUSIBLE_MEDIAN_DEPTH_M
    if low <= median <= high:
        return
    hint = (
        "are these millimetres read as metres?"
        if median > high
        else "is depth_units_per_metre too large?"
    )
    raise DataError(
        f"{path}: median depth {median:.3g} m at depth_units_per_metre={units_per_metre:g}, "
        f"outside {low:g}-{high:g} m: the depth scale looks wrong ({hint} 7-Scenes "
        "stores millimetres: 1000, TUM RGB-D 5000)"
    )


def positive_scale(units_per_metre: object) -> float:
    """`units_per_metre` as a positive finite float, or a ConfigError naming it."""
    valid = isinstance(units_per_metre, int | float | np.number) and not isinstance(
        units_per_metre, bool
    )
    if not valid or not math.isfinite(units_per_metre) or units_per_metre <= 0:
        raise ConfigError(
            f"units_per_metre must be a positive number (1000 for millimetres), "
            f"got {units_per_metre!r}"
        )
    return float(units_per_metre)


def read_frame_depth(frame: Frame) -> np.ndarray | None:
    """The depth map of a dataset frame in metres, or None when the frame has none.

    The map must have the size of the frame's depth camera where it has one (the
    depth is then not registered to the image: relocfw.structure.registration), else
    of its camera (the colour image's full resolution): a depth map of another size
    is not the one described, and lifting keypoints with it would be silently wrong.

    Args:
        frame: a Frame; its `depth_path` and `depth_units_per_metre` are used.

    Returns:
        [H, W] float32 z in metres, NaN where there is no reading (see read_depth);
        None when `frame.depth_path` is None.

    Raises:
        DataError: naming the depth file when it is missing, not a 16-bit
            single-channel image, or not the (depth) camera's size.
    """
    if frame.depth_path is None:
        return None
    camera = frame.depth_camera or frame.camera
    size = None if camera is None else (camera.width, camera.height)
    return read_depth(frame.depth_path, size, frame.depth_units_per_metre)


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


def encode_depth(depth: np.ndarray, units_per_metre: float = MILLIMETRES_PER_METRE) -> np.ndarray:
    """The 16-bit pixels of a depth map in metres, as `read_depth` reads them back.

    Args:
        depth: [H, W] z in metres; NaN, infinite, not positive or beyond what 16 bits
            hold (65.534 m in millimetres) means no reading.
        units_per_metre: what one metre is stored as (1000: millimetres).

    Returns:
        [H, W] uint16, rounded to the nearest unit; 0 where there is no reading (never
        65535, which read_depth also takes as none).

    Raises:
        ConfigError: when `units_per_metre` is not a positive finite number.
    """
    scale = positive_scale(units_per_metre)
    units = np.rint(np.asarray(depth, dtype=np.float64) * scale)
    # NaN compares False, so it falls outside `valid` with the rest.
    valid = (units >= 1) & (units <= np.iinfo(np.uint16).max - 1)
    return np.where(valid, units, 0).astype(np.uint16)


def write_depth(
    path: str | Path, depth: np.ndarray, units_per_metre: float = MILLIMETRES_PER_METRE
) -> None:
    """Write a depth map in metres as a 16-bit PNG (see encode_depth).

    Raises:
        DataError: naming the file when it cannot be written.
    """
    path = Path(path)
    pixels = encode_depth(depth, units_per_metre)
    try:
        written = cv2.imwrite(str(path), pixels)
    except cv2.error as error:  # e.g. an extension OpenCV cannot write 16 bits to
        raise DataError(f"cannot write depth map: {path} ({error})") from error
    if not written:
        raise DataError(f"cannot write depth map: {path}")
