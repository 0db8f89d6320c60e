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

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.standardise import ZScore
from relocfw.structure.absolute_pose import POSELIB_MAX_ITERATIONS
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
                options[key] = integer_at_least(f"refine.{key}", value, STATE_INTEGERS[key])
                if key == "ransac_min_iterations":
                    options[key] = checked_min_iterations(value)
        for key in STATE_NUMBERS:
            if key in state:
                value = float(checked_tensor(state, key, torch.float64, STATE_LABEL))
                at_most_one = key in ("ratio", "image_scale")
                options[key] = positive_number(
                    f"refine.{key}", value, **({"most": 1.0} if at_most_one else {})
                )
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
