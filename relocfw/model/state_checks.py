"""Checks of a network's saved state before the network is built for real.

A model file stores a network's constructor options beside its weights, and both are
data from anyone. Built from crafted options (feature_dim=10**9) the network would
allocate terabytes before load_state_dict could say the weights do not fit. Built on
torch's meta device first, it has every shape and no storage: options that do not fit
the saved weights are refused for nothing, and options that fit allocate no more than
the file itself holds.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import nn


def state_mismatch(build: Callable[[], nn.Module], state: Mapping[str, torch.Tensor]) -> str | None:
    """What differs between the state `build()` makes and `state`; None if nothing does.

    `build` runs on the meta device (no memory for its tensors) with torch's random
    stream left as it was. A module whose construction has no meta kernel
    (NotImplementedError) cannot be checked this way: None, and loading it
    (load_state_dict, strict) still refuses weights that do not fit.

    Raises:
        whatever `build` raises for its options (e.g. ConfigError), and RuntimeError
        where the shapes overflow even as sizes.
    """
    try:
        with torch.random.fork_rng(devices=[]), torch.device("meta"):
            expected = build().state_dict()
    except NotImplementedError:
        return None
    missing = [key for key in expected if key not in state]
    if missing:
        return f"{len(missing)} weights missing, e.g. {missing[0]}"
    unexpected = [key for key in state if key not in expected]
    if unexpected:
        return f"{len(unexpected)} weights it does not have, e.g. {unexpected[0]}"
    for key, tensor in expected.items():
        if tuple(state[key].shape) != tuple(tensor.shape):
            return (
                f"{key} is {list(state[key].shape)} in the file, the options make it "
                f"{list(tensor.shape)}"
            )
    return None


def tensor_mapping(state: Any) -> str | None:
    """What keeps `state` from being a mapping of names to tensors; None if nothing."""
    if not isinstance(state, Mapping):
        return f"the state is {type(state).__name__}, not a mapping of tensors"
    for key, value in state.items():
        if not isinstance(key, str) or not isinstance(value, torch.Tensor):
            return f"the state's {key!r} is {type(value).__name__}, not a tensor"
    return None


def first_non_finite(state: Mapping[str, torch.Tensor]) -> str | None:
    """The first key of `state` whose floating-point values hold NaN or infinity."""
    for key, value in state.items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            return key
    return None
