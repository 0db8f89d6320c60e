"""PoseNet's loss over all heads, with a fixed or a learned position/orientation balance.

Fixed (PoseNet, Kendall et al. 2015): ||x - x^|| + beta ||q - q^/|q^| ||.
Learned (Kendall & Cipolla 2017): ||x - x^|| exp(-s_x) + s_x + ||q - q^|| exp(-s_q) + s_q,
with s_x, s_q trained alongside the network: the homoscedastic uncertainty of each
task sets its weight, so no beta has to be searched per scene.
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
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batch means of ||x - x^|| (metres) and ||q - q^/|q^| ||."""
    position_error = torch.linalg.vector_norm(positions - true_positions, dim=1).mean()
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
) -> torch.Tensor:
    """Weighted sum over heads (paper: 0.3, 0.3 for the auxiliaries, 1 for the main).

    Args:
        parts: if given, filled with each head's weighted loss ("main", "aux1",
            "aux2") and the main head's position (m) and orientation errors, detached,
            for training curves.
    """
    heads = [("main", 1.0, output.positions, output.quaternions)]
    heads += [
        (f"aux{i + 1}", w, p, q)
        for i, (w, (p, q)) in enumerate(zip(auxiliary_weights, output.auxiliary, strict=False))
    ]
    total = torch.zeros((), device=output.positions.device)
    for name, weight, positions, quaternions in heads:
        errors = head_errors(positions, quaternions, true_positions, true_quaternions)
        head_loss = weight * weighting(*errors)
        total = total + head_loss
        if parts is not None:
            parts[name] = head_loss.detach()
            if name == "main":
                parts["main_position_m"], parts["main_orientation"] = (e.detach() for e in errors)
    return total
