"""Checks of array arguments at public entries: one DataError naming the argument.

Point sets are [N, k] rows (pixels k = 2, points k = 3); a NaN row is dropped by the
caller, who knows why it is NaN (a keypoint without depth), never passed on to poison a
solver.
"""

from __future__ import annotations

import numpy as np

from relocfw.core.errors import DataError

WHAT = {2: "pixels", 3: "points"}


def point_rows(values: object, name: str, columns: int, finite: bool = True) -> np.ndarray:
    """`values` as an [N, columns] float64 array (of finite numbers when `finite`), or a
    DataError naming `name` and what is wrong: not numbers, the shape, or how many rows
    hold NaN or infinity."""
    what = WHAT.get(columns, "numbers")
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{name} must be an [N, {columns}] array of numbers") from None
    if array.ndim != 2 or array.shape[1] != columns:
        shape = array.shape
        raise DataError(f"{name} must be an [N, {columns}] array of {what}, got shape {shape}")
    if finite and not np.isfinite(array).all():
        bad = int((~np.isfinite(array).all(axis=1)).sum())
        raise DataError(f"{name} has {bad} rows with NaN or infinity; drop them first")
    return array
