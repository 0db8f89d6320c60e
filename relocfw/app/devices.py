"""The torch device `device=` names, checked before any work."""

from __future__ import annotations

import torch

from relocfw.core.errors import ConfigError


def pick_device(name: str) -> torch.device:
    """The torch device that `device=` names, checked to exist on this machine.

    Checked before any data is read or model built: a device that is not there would
    otherwise fail deep inside torch, with a traceback, after minutes of work.

    Raises:
        ConfigError: naming `device`, for a malformed name, a missing CUDA or MPS, or
            a CUDA index beyond the devices this machine has.
    """
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as error:  # TypeError: device=null
        raise ConfigError(
            f"device={name} is not a device name; use cpu, cuda, cuda:N or mps"
        ) from error
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device={name}, but CUDA is not available here; use device=cpu")
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise ConfigError(
                f"device={name}, but this machine has {count} CUDA device(s): "
                f"use cuda:0 to cuda:{count - 1}"
            )
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise ConfigError(f"device={name}, but MPS is not available here; use device=cpu")
    return device
