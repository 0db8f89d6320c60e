"""The validation block that calibrates error bounds (the `calibrate:` options): carved
from the end of the training split, before the network trains or the map is built."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from omegaconf import DictConfig

from relocfw.core.error_bounds import checked_coverage
from relocfw.core.errors import ConfigError
from relocfw.core.options import integer_at_least, positive_number
from relocfw.data.frames import Frame
from relocfw.report.calibration import Calibration

# Fewer held-out answers say little about the coverage a robot will see; a coverage
# c needs at least c / (1 - c) of them for any finite bound (9 at 90%).
MIN_VALIDATION_FRAMES = 10
# Most of the training split must stay in the map and the network's training.
MAX_SHARE = 0.5

Split = tuple[list[Frame], list[np.ndarray]]


@dataclass(frozen=True)
class CalibrateOptions:
    """The `calibrate:` options, checked."""

    share: float
    coverage: float
    bins: int


def calibrate_options(cfg: DictConfig) -> CalibrateOptions:
    """The `calibrate:` options, each checked and named as the command line spells it
    (before any image is read or model trained, also when share is 0: a typo in a
    coverage is an error, not a silent default)."""
    calibrate = cfg.get("calibrate") or {}
    coverage = checked_coverage(
        float(calibrate.get("coverage", 0.9)), "calibrate.coverage", ConfigError
    )
    bins = integer_at_least("calibrate.bins", calibrate.get("bins", 3), 1)
    share = float(calibrate.get("share", 0.0) or 0.0)
    if share != 0.0:
        share = positive_number("calibrate.share", share, most=MAX_SHARE)
    return CalibrateOptions(share, coverage, bins)


def carve_validation(cfg: DictConfig, train: Split) -> tuple[Split, Calibration | None]:
    """The training split without its validation block, and the block (None when
    calibrate.share is 0).

    The block is the last `share` of the training frames in the dataset's order, which
    is recording order for 7-Scenes, TUM, folders of numbered frames and ROS bags: a
    contiguous stretch of the camera's path, so its frames are neither in the map nor
    next to a map image on both sides, as a test frame may be. (A random sample would
    put every validation frame between two map images a frame apart, and bound errors
    far smaller than a new query's.)
    """
    options = calibrate_options(cfg)
    if options.share == 0.0:
        return train, None
    share, coverage = options.share, options.coverage
    frames, images = train
    held_out = math.ceil(share * len(frames))
    needed = max(MIN_VALIDATION_FRAMES, math.ceil(coverage / (1.0 - coverage) - 1e-9))
    if held_out < needed:
        raise ConfigError(
            f"calibrate.share={share} holds out {held_out} of the {len(frames)} training "
            f"frames; at least {needed} are needed to calibrate {coverage:.0%} error bounds "
            f"(raise calibrate.share, or set it to 0 for no bounds)"
        )
    kept = len(frames) - held_out
    print(
        f"calibrate: the last {held_out} training frames ({frames[kept].name} .. "
        f"{frames[-1].name}) are held out of training and the map, to calibrate "
        f"{coverage:.0%} error bounds"
    )
    block = Calibration(frames[kept:], images[kept:], coverage, options.bins)
    return (list(frames[:kept]), list(images[:kept])), block


def held_out_count(calibration: Calibration | None) -> int:
    """How many frames the validation block holds (for a model file's metadata)."""
    return 0 if calibration is None else len(calibration.frames)
