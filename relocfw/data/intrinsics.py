"""Reading a camera's 3x3 calibration matrix from a text file (7-Scenes' format)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.data.text import data_lines, numbers


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
