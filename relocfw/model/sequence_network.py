"""A VidLoc-style recurrent pose regressor over the descriptors of consecutive frames.

Clark et al. (VidLoc, CVPR 2017) run a CNN on every frame of a video clip and a
bidirectional LSTM over the per-frame features, regressing each frame's pose; the
recurrence exploits that a camera moves smoothly. Here the per-frame features are a
trained relocfw backbone's descriptors (frozen: on a CPU budget the network is trained
once, the recurrent part in seconds), so any backbone's model gains a sequence row.

`direction`:
- causal: a forward LSTM; frame t's pose depends on frames <= t only, what a robot
  relocalizing as it moves can run.
- bidirectional: VidLoc's forward + backward LSTM; over a clip, frame t's pose also
  depends on the frames after t. The query contract (relocfw.plugins.sequence_refiner)
  answers each query from the clip that ENDS at it, so both stay online.
"""

from __future__ import annotations

import torch
from torch import nn

from relocfw.core.errors import ConfigError

DIRECTIONS = ("causal", "bidirectional")


def checked_direction(direction: str) -> str:
    if direction not in DIRECTIONS:
        raise ConfigError(f"refine.direction must be one of {DIRECTIONS}, got {direction!r}")
    return direction


class SequencePoseNetwork(nn.Module):
    """[B, T, D] standardised descriptors of consecutive frames -> [B, T, 3] normalised
    positions and [B, T, 4] unit quaternions (w first), one per frame.

    Args:
        feature_dim: D, the backbone's descriptor length.
        hidden: the LSTM's state size (per direction).
        direction: "causal" or "bidirectional" (module docstring).
        input_dropout: dropout on the descriptors in training: the map's descriptors
            are those of the images the backbone was trained on, cleaner than any
            query's, and the recurrence must learn not to trust one frame alone.
    """

    def __init__(
        self,
        feature_dim: int,
        hidden: int = 256,
        direction: str = "causal",
        input_dropout: float = 0.2,
    ) -> None:
        super().__init__()
        self.direction = checked_direction(direction)
        # A projection first: an LSTM's gates on 2048 inputs would be 4 x 2048 x hidden
        # weights per direction, most of them fitting noise on a few hundred frames.
        self.project = nn.Sequential(
            nn.Dropout(input_dropout), nn.Linear(feature_dim, hidden), nn.ReLU()
        )
        bidirectional = direction == "bidirectional"
        self.lstm = nn.LSTM(hidden, hidden, batch_first=True, bidirectional=bidirectional)
        outputs = hidden * (2 if bidirectional else 1)
        self.position = nn.Linear(outputs, 3)
        self.orientation = nn.Linear(outputs, 4)

    def forward(self, descriptors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        states, _ = self.lstm(self.project(descriptors))
        quaternions = nn.functional.normalize(self.orientation(states), dim=-1)
        return self.position(states), quaternions
