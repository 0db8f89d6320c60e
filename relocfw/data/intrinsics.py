"""Reading a camera's 3x3 calibration matrix from a text file (7-Scenes' format)."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.core.imaging import read_rgb
from relocfw.data.text import data_lines, numbers

# The file name 7-Scenes gives K; the other loaders read the same name and format.
INTRINSICS_FILE = "camera-intrinsics.txt"
# The folders whose default camera has been noted in this process: one note each,
# however often a split is loaded (compare loads it once per method).
NOTED_FOLDERS: set[Path] = set()


def note_default_camera(folder: Path, camera: PinholeCamera, what: str) -> None:
    """One line on stderr: `folder` has no intrinsics file, so `camera` is used.

    Wrong intrinsics never fail a run; they only make refine=features' poses worse.
    So a loader that falls back to a dataset's nominal camera says so, naming the
    folder, the values and the file that would replace them. Printed as the CLI's
    other notes are (stderr, "note:"), once per folder per process.

    Args:
        folder: the folder that lacks camera-intrinsics.txt.
        camera: the camera used instead.
        what: where its values come from, e.g. "the ROS default intrinsics".
    """
    folder = Path(folder)
    if folder in NOTED_FOLDERS:
        return
    NOTED_FOLDERS.add(folder)
    print(
        f"note: {folder}: no {INTRINSICS_FILE}, so {what} are used: fx={camera.fx:g} "
        f"fy={camera.fy:g} cx={camera.cx:g} cy={camera.cy:g} for "
        f"{camera.width} x {camera.height} images (put your camera's K in "
        f"{folder / INTRINSICS_FILE})",
        file=sys.stderr,
    )


def read_intrinsics_matrix(path: str | Path, width: int, height: int) -> PinholeCamera:
    """The pinhole camera of a text file holding K, one row per line.

    The format of 7-Scenes' `camera-intrinsics.txt`: three lines of three numbers
    (spaces, tabs or commas; exponents such as 5.85e+02), `fx 0 cx / 0 fy cy / 0 0 1`.
    Blank lines and # comments are passed over. The file holds no image size, so the
    caller names the size the matrix was calibrated for.

    Args:
        path: the text file.
        width: width in pixels of the images the matrix belongs to (7-Scenes: 640).
        height: their height in pixels (7-Scenes: 480).

    Returns:
        PinholeCamera(fx, fy, cx, cy, width, height).

    Raises:
        DataError: naming the file (and the line, for a bad row) when it is missing,
            not text, not 3 rows of 3 finite numbers, has a skew or a non-zero entry
            below the diagonal, a bottom row other than 0 0 1, or a focal length that
            is not positive.
        ConfigError: naming `width` or `height` when it is not a positive integer.
    """
    path = Path(path)
    rows = []
    sources = []
    for source, fields in data_lines(path):
        # numbers() names file:line for a wrong count, a non-number, NaN or infinity.
        rows.append(numbers(fields, source, 3))
        sources.append(source)
        if len(rows) > 3:
            raise DataError(f"{source}: a 3x3 matrix has 3 rows; this is a 4th")
    if len(rows) != 3:
        raise DataError(f"{path}: expected a 3x3 matrix (3 rows of 3 numbers), found {len(rows)}")
    k = np.array(rows, dtype=np.float64)
    # Exact zeros and ones: K is written by hand or by a calibration tool, and any
    # other value means a different camera model (skewed or projective), not rounding.
    if k[0, 1] != 0:
        raise DataError(
            f"{sources[0]}: skew K[0,1] = {k[0, 1]:g}; relocfw's pinhole camera has none (0)"
        )
    if k[1, 0] != 0:
        raise DataError(f"{sources[1]}: K[1,0] = {k[1, 0]:g}, expected 0 (not a calibration K)")
    if list(k[2]) != [0.0, 0.0, 1.0]:
        found = " ".join(f"{v:g}" for v in k[2])
        raise DataError(f"{sources[2]}: bottom row must be 0 0 1, got {found}")
    for name, value, source in (("fx", k[0, 0], sources[0]), ("fy", k[1, 1], sources[1])):
        if value <= 0:
            raise DataError(f"{source}: focal length {name} = {value:g}, expected > 0")
    return PinholeCamera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)


def image_size(images: Sequence[Path]) -> tuple[int, int]:
    """(width, height) of the first of `images` that decodes.

    One image is decoded, not all: a dataset's camera has one size. An image that does
    not decode is passed over here (reading the images names it later, under the
    dataset's on_error rule), so one bad frame does not stop a whole split.

    Raises:
        DataError: when none of `images` decodes (naming the first), or there are none.
    """
    for path in images:
        try:
            height, width = read_rgb(path).shape[:2]
        except DataError:
            continue
        return width, height
    raise DataError(
        "no image decodes, so the size of the camera cannot be known"
        + (f" (first: {images[0]})" if images else "")
    )


def read_camera_for_images(path: str | Path, images: Sequence[Path]) -> PinholeCamera:
    """The camera of an intrinsics file (7-Scenes' format) for the images it belongs to.

    The file holds K but no image size; the size is that of the first image that
    decodes (one decode per call, not per frame). Taking 2 cx x 2 cy instead would be
    one pixel off for a principal point at the exact centre, (W - 1) / 2.

    Args:
        path: the camera-intrinsics.txt.
        images: the colour images the file describes, in dataset order.

    Returns:
        PinholeCamera of the file's K, width and height of the images.

    Raises:
        DataError: naming the file for a malformed matrix (read_intrinsics_matrix), or
            naming an image when none of `images` decodes.
    """
    # The file is checked before any image is decoded, so a malformed file is named
    # even when the images are unreadable too; the size is filled in afterwards.
    unsized = read_intrinsics_matrix(path, 1, 1)
    width, height = image_size(images)
    return replace(unsized, width=width, height=height)


def write_intrinsics_matrix(path: str | Path, camera: PinholeCamera) -> None:
    """K of `camera` in 7-Scenes' format: three rows of three numbers, %.18e, spaces.

    The size is not written (the format has none); %.18e reads back to the same floats.
    """
    rows = camera.matrix()
    Path(path).write_text("".join(" ".join(f"{v:.18e}" for v in row) + "\n" for row in rows))
