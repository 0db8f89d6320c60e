"""Checks of the dataset options shared by several loaders, named as the command line
spells them (dataset.metric, dataset.depth_units_per_metre)."""

from __future__ import annotations

import math

import numpy as np

from relocfw.core.errors import ConfigError


def metric_option(value: object) -> bool:
    """`dataset.metric` as a bool, or a ConfigError naming the key.

    True: the poses are metres (in one world frame across laps), so reports speak of
    metres; False: model units (relocfw.report.units), as for an unaligned COLMAP model.
    """
    if not isinstance(value, bool):
        raise ConfigError(f"dataset.metric must be true or false, got {value!r}")
    return value


def depth_units_option(value: object) -> float:
    """`dataset.depth_units_per_metre` as a positive finite float, or a ConfigError
    naming the key (read_depth would name only `units_per_metre`, and only once a depth
    map is read, after training)."""
    number = isinstance(value, int | float | np.number) and not isinstance(value, bool)
    if not number or not math.isfinite(value) or value <= 0:
        raise ConfigError(
            "dataset.depth_units_per_metre must be a positive number (5000 for TUM RGB-D, "
            f"1000 for millimetre PNGs such as a RealSense's), got {value!r}"
        )
    return float(value)
