"""Each part of a model file rebuilt from its stored options and state, checked first.

A model file is data from anyone: its options and arrays are checked before they are
used (sizes before anything is allocated, shapes against the weights, values finite),
and every way a part fails ends in one DataError naming the file and the part
(relocfw.model.model_file.load_model calls these once the part's class is known to
be a registered plugin).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError, RelocfwError
from relocfw.core.interfaces import Backbone, CropSearch, SimilarityIndex
from relocfw.core.refinement import PoseRefiner
from relocfw.core.values import Pose
from relocfw.model.state_checks import first_non_finite, state_mismatch, tensor_mapping

# The largest number a stored network option may hold (feature_dim, input_size,
# mc_samples, each of decoder_channels): far above any relocfw network (2048, 224, 40,
# 256), far below sizes that overflow, or run for hours, before anything checks them.
# The weights bound the rest (stored_backbone).
MAX_BACKBONE_OPTION = 65536
# The option names that say a size, the ones MAX_BACKBONE_OPTION caps.
SIZE_OPTION = re.compile(r"size|dim|channels|samples|hidden|width|depth|layers", re.IGNORECASE)

# How a part (relocfw's or a third party's) may fail on crafted options or state.
PART_FAILURES = (
    ConfigError,
    DataError,
    KeyError,
    TypeError,
    ValueError,
    AttributeError,
    RuntimeError,
    NotImplementedError,
)


def damaged(path: Path, detail: str) -> DataError:
    """The one-line DataError for a model file damaged as `detail` says."""
    return DataError(f"{path}: damaged model file ({detail})")


@contextmanager
def building(path: Path, group: str) -> Iterator[None]:
    """Turns any way part `group` fails on its options or state into one DataError
    naming the file and the part."""
    try:
        yield
    except PART_FAILURES as error:
        # relocfw's own errors are sentences; anything else also says what it was.
        said = str(error) if isinstance(error, RelocfwError) else repr(error)
        raise damaged(path, f"{group}: {said}") from error


def stored_backbone(payload: dict[str, Any], backbone_class: type, path: Path) -> Backbone:
    """The file's network with its weights, its options checked before it is built.

    No size option may hold a number above MAX_BACKBONE_OPTION, and the shapes the options
    make (built on the meta device: no memory) must be the weights': crafted options
    (feature_dim=10**9) are refused before they allocate, and options that fit
    allocate no more than the file holds. Weights holding NaN or infinity are refused
    too: every pose would be NaN.
    """
    state = payload["backbone"].get("state")
    if (wrong := tensor_mapping(state)) is not None:
        raise damaged(path, f"backbone: {wrong}")
    options = {**payload["backbone"]["options"], **backbone_class.rebuild_overrides}
    if (oversized := oversized_option(options)) is not None:
        raise damaged(path, f"backbone: option {oversized} is above {MAX_BACKBONE_OPTION}")
    with building(path, "backbone"):
        mismatch = state_mismatch(lambda: backbone_class(**options), state)
    if mismatch is not None:
        raise damaged(path, f"backbone: its options do not fit its weights ({mismatch})")
    if (key := first_non_finite(state)) is not None:
        raise damaged(path, f"backbone: {key} holds NaN or infinite values")
    with building(path, "backbone"):
        backbone = backbone_class(**options)
        backbone.load_state_dict(state)
    return backbone


def oversized_option(options: dict[str, Any]) -> str | None:
    """The first size option (name=value) holding a number above MAX_BACKBONE_OPTION,
    itself or in a list; None if none does.

    Only options named as sizes (SIZE_OPTION: input_size, feature_dim, mc_samples,
    decoder_channels, a plugin's hidden_dim, ...) are capped: a third party's seed
    or step count may rightly be large, and the weights bound what allocates
    memory anyway (state_mismatch on the meta device)."""
    for name, value in options.items():
        if not SIZE_OPTION.search(name):
            continue
        for number in value if isinstance(value, list | tuple) else [value]:
            if isinstance(number, int | float) and not abs(number) <= MAX_BACKBONE_OPTION:
                return f"{name}={value!r}"
    return None


def stored_index(payload: dict[str, Any], index_class: type, path: Path) -> SimilarityIndex:
    """The file's similarity index, given its state (the map)."""
    part = payload["index"]
    with building(path, "index"):
        index = index_class(**part["options"])
        index.load_state(part["state"])
    return index


def check_descriptor_dims(backbone: Backbone, index: SimilarityIndex, path: Path) -> None:
    """A DataError when the index's map is of other descriptors than the network
    makes (an index that says its `dim`); each would load, and fail at the first query."""
    made, held = getattr(backbone, "feature_dim", None), getattr(index, "dim", None)
    if isinstance(made, int) and isinstance(held, int) and made != held:
        raise damaged(
            path, f"index: its map holds {held}-dimensional descriptors, the backbone makes {made}"
        )


def stored_crop(payload: dict[str, Any], crop_class: type, path: Path) -> CropSearch:
    """The file's crop search, given its state where it keeps the map (crop=rule)."""
    part = payload["crop"]
    with building(path, "crop"):
        crop = crop_class(**part["options"])
        if crop.wants_map:
            crop.load_state(part["state"])
    return crop


def stored_refiner(
    payload: dict[str, Any], classes: dict[str, type], path: Path
) -> PoseRefiner | None:
    """The file's refiner, rebuilt and given its state (fitted); None without one.

    The refiner's `load_state` checks each tensor's dtype, shape and values (format 5:
    a features refiner's whole map structure), and any fault is one DataError naming
    the refine part."""
    if "refine" not in classes:
        return None
    part = payload["refine"]
    with building(path, "refine"):
        refiner = classes["refine"](**part["options"])
        refiner.load_state(part["state"])
    return refiner


def stored_map_poses(payload: dict[str, Any], path: Path) -> list[Pose] | None:
    """The map images' poses the file stores ([N, 7] position and quaternion), or None."""
    if "map_poses" not in payload:
        return None
    poses = payload["map_poses"]
    if not isinstance(poses, torch.Tensor):
        raise damaged(path, f"map_poses must be an [N, 7] tensor, got a {type(poses).__name__}")
    if poses.ndim != 2 or poses.shape[1] != 7:
        raise damaged(path, f"map_poses must be an [N, 7] tensor, got shape {list(poses.shape)}")
    rows = poses.double().numpy()
    if not np.isfinite(rows).all():
        raise damaged(path, "map_poses hold NaN or infinite values")
    return [Pose(row[:3], row[3:]) for row in rows]


def stored_metadata(payload: dict[str, Any], path: Path) -> dict[str, Any]:
    """The file's description of its data (save_model's `metadata`)."""
    metadata = payload.get("metadata")
    if not isinstance(metadata, dict):
        raise damaged(path, f"metadata must be a mapping, got {type(metadata).__name__}")
    return metadata
