"""What the network answers for a batch of windows, as float64 numpy arrays."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch


class NetworkAnswers(NamedTuple):
    """The backbone's outputs for a batch of windows, as float64 numpy arrays."""

    positions: np.ndarray  # [n, 3]
    quaternions: np.ndarray  # [n, 4]
    features: np.ndarray  # [n, D]
    position_spread: np.ndarray  # [n], NaN unless the backbone samples
    orientation_spread_deg: np.ndarray  # [n]

    def row(self, i: int) -> NetworkAnswers:
        """The answers of window i alone."""
        return NetworkAnswers(*(column[i] for column in self))


def as_numpy(tensor: torch.Tensor | None, count: int) -> np.ndarray:
    if tensor is None:
        return np.full(count, np.nan)
    return tensor.double().cpu().numpy()
