"""PoseNet's loss: position error plus beta times quaternion error, over all heads."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from relocfw.values import PoseOutput


def head_loss(
    positions: torch.Tensor,
    quaternions: torch.Tensor,
    true_positions: torch.Tensor,
    true_quaternions: torch.Tensor,
    beta: float,
) -> torch.Tensor:
    """Mean over the batch of ||x - x_hat|| + beta * ||q - q_hat / |q_hat| ||."""
    position_term = torch.linalg.vector_norm(positions - true_positions, dim=1)
    unit = torch.nn.functional.normalize(quaternions, dim=1)
    orientation_term = torch.linalg.vector_norm(unit - true_quaternions, dim=1)
    return (position_term + beta * orientation_term).mean()


def posenet_loss(
    output: PoseOutput,
    true_positions: torch.Tensor,
    true_quaternions: torch.Tensor,
    beta: float,
    auxiliary_weights: Sequence[float] = (0.3, 0.3),
) -> torch.Tensor:
    """Weighted sum over heads (paper: 0.3, 0.3 for the auxiliaries, 1 for the main)."""
    total = head_loss(output.positions, output.quaternions, true_positions, true_quaternions, beta)
    for weight, (positions, quaternions) in zip(auxiliary_weights, output.auxiliary, strict=False):
        total = total + weight * head_loss(
            positions, quaternions, true_positions, true_quaternions, beta
        )
    return total
