"""The keyframes a query is matched against, checked (shared by the query solver and
the map's MatchIndex, which the solver imports)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from relocfw.core.errors import DataError


def checked_keyframes(keyframes: Sequence[int], count: int) -> list[int]:
    """`keyframes` as distinct ints in [0, count), first occurrences in order.

    A repeated keyframe would add the same correspondences twice and weigh them
    double in the solve, so repeats are dropped.

    Raises:
        DataError: naming the entry that is not an integer index of the map.
    """
    if isinstance(keyframes, str | bytes) or not isinstance(keyframes, Sequence | np.ndarray):
        raise DataError(f"keyframes must be a sequence of map indices, got {keyframes!r}")
    chosen: list[int] = []
    for number, index in enumerate(keyframes):
        if isinstance(index, bool) or not isinstance(index, int | np.integer):
            raise DataError(f"keyframes[{number}] must be an integer index, got {index!r}")
        if not 0 <= int(index) < count:
            raise DataError(
                f"keyframes[{number}] = {int(index)} is not an image of the map (0 .. {count - 1})"
            )
        if int(index) not in chosen:
            chosen.append(int(index))
    return chosen
