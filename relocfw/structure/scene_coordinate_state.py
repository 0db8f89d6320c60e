"""What a model file keeps of refine=scene_coordinates, and its checks on loading.

Plain tensors only (torch's weights-only loader reads model files): the head's
state_dict under "head.<name>" (weights, input standardisation, scene mean), its
sizes (`channels`, `head_width`, `head_layers`), the query options, and the map's
one camera (`camera`: [fx, fy, cx, cy, width, height], or empty where the map images
have several). A file is data from anyone: every tensor's dtype, shape and values are
checked, and the head's shapes are compared on torch's meta device before anything is
allocated from the stored sizes (relocfw.model.state_checks does the same for
networks; that module is not importable from here, so the check is repeated in
small). A fault is one DataError naming the tensor.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import integer_at_least, positive_number
from relocfw.structure.map_state import camera_of_row, checked_tensor
from relocfw.structure.refiner_state import checked_min_iterations
from relocfw.structure.scene_coordinate_head import SceneCoordinateHead, built_head

STATE_LABEL = "refine=scene_coordinates state"
# The integer options a state keeps, with their least values; and the numbers.
INTEGERS = {
    "encoder": 0,
    "image_size": 16,
    "min_inliers": 4,
    "ransac_min_iterations": 1,
    "used_depth": 0,
    "channels": 1,
    "head_width": 1,
    "head_layers": 1,
}
NUMBERS = ("max_error_px",)
# Far above any useful head (about 1 GB of float32 weights at 16384 wide): a crafted
# size is refused before the meta build works out shapes from it.
MOST_WIDTH = 16384
MOST_LAYERS = 64
# The encoder image's shorter side: 4096 px is beyond any camera this serves, and a
# crafted file's size would otherwise be allocated by the first query's resize.
MOST_IMAGE_SIZE = 4096


def head_state(
    head: SceneCoordinateHead, options: Mapping[str, float], camera: PinholeCamera | None
) -> dict[str, torch.Tensor]:
    """The head, its sizes, `options` (INTEGERS and NUMBERS keys) and the map camera."""
    state = {f"head.{key}": value.detach().clone() for key, value in head.state_dict().items()}
    sizes = {"channels": head.channels, "head_width": head.width, "head_layers": head.layers}
    state |= {key: torch.tensor(int(value)) for key, value in sizes.items()}
    state |= {key: torch.tensor(int(options[key])) for key in INTEGERS if key not in sizes}
    state |= {key: torch.tensor(float(options[key]), dtype=torch.float64) for key in NUMBERS}
    row = [] if camera is None else [camera.fx, camera.fy, camera.cx, camera.cy]
    row += [] if camera is None else [camera.width, camera.height]
    state["camera"] = torch.tensor(row, dtype=torch.float64)
    return state


def stored_options(state: Mapping[str, torch.Tensor], encoders: Sequence[str]) -> dict:
    """The integer and number options, each checked as the command line's would be."""
    options: dict = {}
    try:
        for key, least in INTEGERS.items():
            value = checked_tensor(state, key, torch.int64, STATE_LABEL)
            if value.shape != ():
                raise DataError(
                    f"{STATE_LABEL}: {key} must be one integer, got {list(value.shape)}"
                )
            options[key] = integer_at_least(f"refine.{key}", int(value), least)
        for key in NUMBERS:
            value = checked_tensor(state, key, torch.float64, STATE_LABEL)
            if value.shape != ():
                raise DataError(f"{STATE_LABEL}: {key} must be one number, got {list(value.shape)}")
            options[key] = positive_number(f"refine.{key}", float(value))
        checked_min_iterations(options["ransac_min_iterations"])
    except ConfigError as error:
        raise DataError(f"{STATE_LABEL}: {error}") from None
    if options["image_size"] > MOST_IMAGE_SIZE:
        raise DataError(
            f"{STATE_LABEL}: image_size must be at most {MOST_IMAGE_SIZE}, "
            f"got {options['image_size']}"
        )
    if options["encoder"] >= len(encoders):
        codes = ", ".join(f"{n} {name}" for n, name in enumerate(encoders))
        raise DataError(f"{STATE_LABEL}: encoder must be one of {codes}, got {options['encoder']}")
    if options["used_depth"] not in (0, 1):
        raise DataError(f"{STATE_LABEL}: used_depth must be 0 or 1, got {options['used_depth']}")
    if options["head_width"] > MOST_WIDTH or options["head_layers"] > MOST_LAYERS:
        raise DataError(
            f"{STATE_LABEL}: head_width {options['head_width']} or head_layers "
            f"{options['head_layers']} above {MOST_WIDTH} / {MOST_LAYERS}"
        )
    return options


def stored_camera(state: Mapping[str, torch.Tensor]) -> PinholeCamera | None:
    """The map's one camera, None where the state keeps none (several cameras)."""
    row = checked_tensor(state, "camera", torch.float64, STATE_LABEL)
    if row.shape == (0,):
        return None
    if row.shape != (6,) or not np.isfinite(row).all():
        raise DataError(
            f"{STATE_LABEL}: camera must be 6 finite values (fx, fy, cx, cy, width, "
            f"height) or none, got {list(row.shape)}"
        )
    return camera_of_row(row, 0, STATE_LABEL)


def head_of_state(
    state: Mapping[str, torch.Tensor], encoders: Sequence[str], channels: Mapping[str, int]
) -> tuple[SceneCoordinateHead, dict, PinholeCamera | None]:
    """The head a state keeps, its options and the map camera, every tensor checked.

    Args:
        state: what `head_state` returned (from a file anyone may have written).
        encoders: the encoder choices, in the order their codes index.
        channels: each encoder's feature channels (the head's input must match).
    """
    if not isinstance(state, Mapping):
        raise DataError(f"{STATE_LABEL}: the state is {type(state).__name__}, not a mapping")
    options = stored_options(state, encoders)
    wanted = channels[encoders[options["encoder"]]]
    if options["channels"] != wanted:
        raise DataError(
            f"{STATE_LABEL}: channels is {options['channels']} but encoder "
            f"{encoders[options['encoder']]} gives {wanted}"
        )
    sizes = (options["channels"], options["head_width"], options["head_layers"])
    weights = {key[5:]: value for key, value in state.items() if key.startswith("head.")}
    with torch.device("meta"):
        expected = built_head(*sizes).state_dict()
    for key, tensor in expected.items():
        value = weights.get(key)
        if not isinstance(value, torch.Tensor):
            raise DataError(
                f"{STATE_LABEL}: head.{key} must be a tensor, got {type(value).__name__}"
            )
        if value.dtype != torch.float32 or tuple(value.shape) != tuple(tensor.shape):
            raise DataError(
                f"{STATE_LABEL}: head.{key} must be float32 {list(tensor.shape)}, got "
                f"{value.dtype} {list(value.shape)}"
            )
        if not bool(torch.isfinite(value).all()):
            raise DataError(f"{STATE_LABEL}: head.{key} holds NaN or infinite values")
    extra = sorted(set(weights) - set(expected))
    if extra:
        raise DataError(f"{STATE_LABEL}: head.{extra[0]} is not a weight of the head")
    if not bool((weights["input_std"] > 0).all()):
        raise DataError(f"{STATE_LABEL}: head.input_std must be above 0")
    head = built_head(*sizes)
    head.load_state_dict(weights, strict=True)
    return head.eval(), options, stored_camera(state)
