"""PoseNet's loss over all heads, with a fixed or a learned position/orientation balance.

Fixed (PoseNet, Kendall et al. 2015): ||x - x^|| + beta ||q - q^/|q^| ||.
Learned (Kendall & Cipolla 2017): ||x - x^|| exp(-s_x) + s_x + ||q - q^|| exp(-s_q) + s_q,
with s_x, s_q trained alongside the network: the homoscedastic uncertainty of each
task sets its weight, so no beta has to be searched per scene.

The position error is measured in units of `position_scale` (training takes the
spread of the training positions, the frame the network regresses in), so beta
weighs the same thing in a scene mapped in metres, millimetres or COLMAP's arbitrary
units: a model trained on a scaled copy of a scene is the same model. PoseNet's own
beta (metres) is `position_scale=1` (train.position_frame=world).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from relocfw.core.values import PoseOutput


def head_errors(
    positions: torch.Tensor,
    quaternions: torch.Tensor,
    true_positions: torch.Tensor,
    true_quaternions: torch.Tensor,
    position_scale: float | torch.Tensor = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batch means of ||x - x^|| / position_scale and ||q - q^/|q^| ||."""
    offsets = positions - true_positions
    position_error = torch.linalg.vector_norm(offsets, dim=1).mean() / position_scale
    unit = nn.functional.normalize(quaternions, dim=1)
    orientation_error = torch.linalg.vector_norm(unit - true_quaternions, dim=1).mean()
    return position_error, orientation_error


class FixedWeighting(nn.Module):
    """position + beta * orientation; beta is chosen by hand (paper: 120-750 indoors)."""

    def __init__(self, beta: float) -> None:
        super().__init__()
        self.beta = float(beta)

    def forward(self, position: torch.Tensor, orientation: torch.Tensor) -> torch.Tensor:
        return position + self.beta * orientation


class LearnedWeighting(nn.Module):
    """Homoscedastic task weighting; s = log of each task's variance, learned.

    Args:
        s_position: initial s_x (Kendall & Cipolla 2017: 0).
        s_orientation: initial s_q (Kendall & Cipolla 2017: -3).
    """

    def __init__(self, s_position: float = 0.0, s_orientation: float = -3.0) -> None:
        super().__init__()
        self.s_position = nn.Parameter(torch.tensor(float(s_position)))
        self.s_orientation = nn.Parameter(torch.tensor(float(s_orientation)))

    def forward(self, position: torch.Tensor, orientation: torch.Tensor) -> torch.Tensor:
        return (
            position * torch.exp(-self.s_position)
            + self.s_position
            + orientation * torch.exp(-self.s_orientation)
            + self.s_orientation
        )


def posenet_loss(
    output: PoseOutput,
    true_positions: torch.Tensor,
    true_quaternions: torch.Tensor,
    weighting: nn.Module,
    auxiliary_weights: Sequence[float] = (0.3, 0.3),
    parts: dict[str, torch.Tensor] | None = None,
    position_scale: float | torch.Tensor = 1.0,
) -> torch.Tensor:
    """Weighted sum over heads (paper: 0.3, 0.3 for the auxiliaries, 1 for the main).

    Args:
        parts: if given, filled with each head's weighted loss ("main", "aux1",
            "aux2") and the main head's position error (world units, not divided by
            `position_scale`) and orientation error, detached, for training curves.
        position_scale: the unit position errors are measured in (see the module).
    """
    heads = [("main", 1.0, output.positions, output.quaternions)]
    heads += [
        (f"aux{i + 1}", w, p, q)
        for i, (w, (p, q)) in enumerate(zip(auxiliary_weights, output.auxiliary, strict=False))
    ]
    total = torch.zeros((), device=output.positions.device)
    for name, weight, positions, quaternions in heads:
        position, orientation = head_errors(
            positions, quaternions, true_positions, true_quaternions, position_scale
        )
        head_loss = weight * weighting(position, orientation)
        total = total + head_loss
        if parts is not None:
            parts[name] = head_loss.detach()
            if name == "main":
                parts["main_position_m"] = (position * position_scale).detach()
                parts["main_orientation"] = orientation.detach()
    return total
