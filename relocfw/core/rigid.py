"""Rigid transforms as 4x4 matrices, checked once where they enter.

A rigid transform maps points of one frame to another: x_to = R x_from + t, held as
[[R, t], [0 0 0 1]]. A calibration file or a dataset's constant (a depth sensor's
pose in the colour camera, relocfw.data.sevenscenes) that is not rigid would bend
every point it moves without any later step noticing, so it is refused here with
one error naming where it came from.
"""

from __future__ import annotations

import numpy as np

from relocfw.core.errors import DataError

# How far R^T R may be from the identity and det R from +1: values typed from a
# calibration with 16 or more digits are orthonormal to about 1e-9; a matrix off
# by more than this is a scale, a shear or a typing error, not rounding.
ORTHONORMAL_TOLERANCE = 1e-6


def checked_rigid(matrix: object, source: str) -> np.ndarray:
    """`matrix` as a read-only 4x4 float64 rigid transform, or a DataError naming `source`.

    Args:
        matrix: a 4x4 array-like [[R, t], [0, 0, 0, 1]].
        source: what gave it (a file, a dataset's constant), named in the error.

    Returns:
        [4, 4] float64 copy with its write flag off, so a frozen value holding it stays
        unchanged.

    Raises:
        DataError: naming `source` when it is not 4x4 numbers, holds NaN or infinity,
            its last row is not 0 0 0 1, or its rotation is not orthonormal with
            determinant +1 (within ORTHONORMAL_TOLERANCE).
    """
    try:
        array = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{source}: a rigid transform must be a 4x4 matrix of numbers") from None
    if array.shape != (4, 4):
        raise DataError(f"{source}: a rigid transform must be 4x4, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise DataError(f"{source}: the rigid transform holds NaN or infinity")
    if not np.array_equal(array[3], [0.0, 0.0, 0.0, 1.0]):
        found = " ".join(f"{v:g}" for v in array[3])
        raise DataError(f"{source}: a rigid transform's last row is 0 0 0 1, got {found}")
    rotation = array[:3, :3]
    off_identity = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    determinant = float(np.linalg.det(rotation))
    if off_identity > ORTHONORMAL_TOLERANCE or abs(determinant - 1.0) > ORTHONORMAL_TOLERANCE:
        raise DataError(
            f"{source}: the rotation part is not a rotation (|R^T R - I| = {off_identity:.2g}, "
            f"det R = {determinant:.6g}; expected orthonormal with det +1 within "
            f"{ORTHONORMAL_TOLERANCE:g}): a rigid transform has no scale, shear or mirror"
        )
    array.setflags(write=False)
    return array


def transform_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[N, 3] points moved by a 4x4 rigid transform: R p + t per row.

    Written as three scaled columns rather than `points @ R.T`: a matrix product with
    an inner size of 3 gains nothing from BLAS, whose threads, on a busy machine,
    made it 5-10 times slower than this (a 640 x 480 depth map: 270k points).
    """
    return (
        points[:, :1] * matrix[:3, 0]
        + points[:, 1:2] * matrix[:3, 1]
        + points[:, 2:3] * matrix[:3, 2]
        + matrix[:3, 3]
    )
