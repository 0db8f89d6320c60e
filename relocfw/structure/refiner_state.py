"""What a model file keeps of refine=features besides the map's structure
(relocfw.structure.map_state): the z-scored map descriptors keyframes are retrieved
by, their standardisation, and the query options.

A fitted refiner's state (plugins/features_refiner.py, `state` / `load_state`) holds
its query options, so a file saved without its options still answers as the run did.
The file is data from anyone: every tensor is checked before use, every option with
the check the command line's would get, and a fault is one DataError naming it.
"""

from __future__ import annotations

import numpy as np
import torch

from relocfw.core.camera import MOST_CAMERA_PIXELS
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.standardise import ZScore
from relocfw.structure.absolute_pose import POSELIB_MAX_ITERATIONS
from relocfw.structure.features import MOST_FEATURES
from relocfw.structure.map_state import checked_tensor

# Stored as its index here: append new choices, never reorder (older files keep
# their codes: 0 descriptor, 1 pose).
KEYFRAMES = ("descriptor", "pose", "track")
# Where the map is held (memory: a StructureMap; compact: a compact map,
# relocfw.structure.compact_cache) and how keyframes are searched by descriptor
# (relocfw.structure.faiss_keyframes). Stored as indices too; a file without them was
# written before they existed and answers as memory / numpy.
MAP_STORES = ("memory", "compact")
KEYFRAME_SEARCHES = ("numpy", "faiss")
# Whether and how a solved query is matched again (plugins/features_refiner.py); a file
# without it was written before it existed and answers as none.
REMATCHES = ("none", "near", "union")
# Which of the two solves answers a matched-again query: the second where it succeeds,
# or the one with more inliers (one per query keypoint); a file without it answers second.
REMATCH_ANSWERS = ("second", "more_inliers")
# The options stored as an index into their choices.
STATE_CHOICES = {
    "keyframes": KEYFRAMES,
    "map_store": MAP_STORES,
    "keyframe_search": KEYFRAME_SEARCHES,
    "rematch": REMATCHES,
    "rematch_answer": REMATCH_ANSWERS,
}
# The integer options a state keeps, with their least values, and the numbers.
STATE_INTEGERS = {"count": 1, "max_features": 8, "min_inliers": 4, "ransac_min_iterations": 1}
STATE_NUMBERS = ("ratio", "max_error_px", "image_scale")
# Upper bounds of the size-like options, far above any use: a model file is data from
# anyone, and a forged size must be refused on loading, not reach OpenCV (SIFT with
# 2**40 features raises at every query) or a loop. An image has at most
# MOST_CAMERA_PIXELS a side, so neither a keypoint count nor an inlier count nor a
# reprojection bound above these means anything.
MOST_KEYFRAMES = 1000
MOST_SIZES = {
    "count": MOST_KEYFRAMES,
    "max_features": MOST_FEATURES,
    "min_inliers": MOST_FEATURES,
    "max_error_px": float(MOST_CAMERA_PIXELS),
}
# Options kept as 0 / 1.
STATE_FLAGS = ("match_points_only",)
STATE_LABEL = "refine=features state"


def checked_min_iterations(value: object) -> int:
    """refine.ransac_min_iterations in 1 .. PoseLib's most rounds, or a ConfigError."""
    rounds = integer_at_least("refine.ransac_min_iterations", value, 1)
    if rounds > POSELIB_MAX_ITERATIONS:
        raise ConfigError(
            f"refine.ransac_min_iterations must be at most {POSELIB_MAX_ITERATIONS} "
            f"(PoseLib's most rounds), got {rounds}"
        )
    return rounds


def checked_size(key: str, value: object, least: int | None = None) -> int | float:
    """refine.<key> (a MOST_SIZES key) within its bounds, or a ConfigError naming it:
    an integer >= `least`, or (least None) a number above 0; at most MOST_SIZES[key]."""
    name = f"refine.{key}"
    number = positive_number(name, value) if least is None else integer_at_least(name, value, least)
    if number > MOST_SIZES[key]:
        raise ConfigError(f"{name} must be at most {MOST_SIZES[key]:g}, got {value!r}")
    return number


def checked_keyframes_choice(keyframes: object) -> str:
    """refine.keyframes as given, or ConfigError listing the choices."""
    return checked_choice("keyframes", keyframes)


def checked_choice(key: str, value: object) -> str:
    """refine.<key> (a STATE_CHOICES key) as given, or ConfigError listing the choices."""
    choices = STATE_CHOICES[key]
    if not isinstance(value, str) or value not in choices:
        raise ConfigError(f"refine.{key} must be one of {', '.join(choices)}, got {value!r}")
    return value


def options_state(options: dict) -> dict[str, torch.Tensor]:
    """`options` (keyframes and every STATE_INTEGERS / STATE_NUMBERS key; map_store,
    keyframe_search and the flags where given) as tensors."""
    state = {
        key: torch.tensor(choices.index(options[key]))
        for key, choices in STATE_CHOICES.items()
        if key in options
    }
    state |= {key: torch.tensor(int(options[key])) for key in STATE_INTEGERS}
    state |= {key: torch.tensor(float(options[key]), dtype=torch.float64) for key in STATE_NUMBERS}
    state |= {key: torch.tensor(int(bool(options[key]))) for key in STATE_FLAGS if key in options}
    return state


def stored_options(state: dict[str, torch.Tensor]) -> dict:
    """The query options a state keeps, each checked as the command line's would be;
    an option the state lacks keeps the constructor's."""
    options: dict = {}
    try:
        for key, choices in STATE_CHOICES.items():
            if key in state:
                code = int(checked_tensor(state, key, torch.int64, STATE_LABEL))
                if not 0 <= code < len(choices):
                    codes = ", ".join(f"{n} {name}" for n, name in enumerate(choices))
                    raise DataError(
                        f"{STATE_LABEL}: {key} must be in 0..{len(choices) - 1} "
                        f"({codes}), got {code}"
                    )
                options[key] = choices[code]
        for key in STATE_INTEGERS:
            if key in state:
                value = int(checked_tensor(state, key, torch.int64, STATE_LABEL))
                if key == "ransac_min_iterations":
                    options[key] = checked_min_iterations(value)
                else:
                    options[key] = checked_size(key, value, STATE_INTEGERS[key])
        for key in STATE_NUMBERS:
            if key in state:
                value = float(checked_tensor(state, key, torch.float64, STATE_LABEL))
                if key in MOST_SIZES:
                    options[key] = checked_size(key, value)
                else:  # ratio and image_scale: shares, at most 1
                    options[key] = positive_number(f"refine.{key}", value, most=1.0)
        for key in STATE_FLAGS:
            if key in state:
                flag = int(checked_tensor(state, key, torch.int64, STATE_LABEL))
                if flag not in (0, 1):
                    raise DataError(f"{STATE_LABEL}: {key} must be 0 or 1, got {flag}")
                options[key] = bool(flag)
    except (ConfigError, TypeError, ValueError) as error:
        raise DataError(f"{STATE_LABEL}: {error}") from None
    return options


def stored_keyframe_descriptors(state: dict[str, torch.Tensor], images: int) -> tuple:
    """The z-scored map descriptors ([images, D] float64, finite) and the ZScore of
    their D dimensions that a state keeps, each checked; DataError naming the tensor."""
    points = checked_tensor(state, "keyframe_descriptors", torch.float64, STATE_LABEL)
    if points.ndim != 2 or len(points) != images:
        raise DataError(
            f"{STATE_LABEL}: keyframe_descriptors must be [{images}, D], one row per map "
            f"image, got {list(points.shape)}"
        )
    if not np.isfinite(points).all():
        raise DataError(f"{STATE_LABEL}: keyframe_descriptors hold NaN or infinite values")
    zscore = ZScore().load_state(state)
    if zscore.mean.shape != (points.shape[1],):
        raise DataError(
            f"{STATE_LABEL}: mean and std must hold {points.shape[1]} values, one per "
            f"descriptor dimension, got {zscore.mean.shape[0]}"
        )
    return points, zscore
