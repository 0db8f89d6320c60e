"""PoseNet's main head, shared by every backbone: descriptor layer, dropout, regressor.

With `mc_samples > 0` the head also runs Bayesian PoseNet's Monte Carlo dropout at
test time: the regressor sees N dropout masks of the same descriptor, the answer is
the mean pose and the spread is the uncertainty. Only the head is sampled, so the
trunk runs once and N = 40 samples cost about one extra matrix product per mask.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from relocfw.core.errors import ConfigError
from relocfw.core.sampling import (  # noqa: F401 (mean_quaternions: its 0.1 path)
    mean_quaternions,
    sample_statistics,
)
from relocfw.core.values import PoseOutput


class PoseRegressor(nn.Module):
    """Position (3) and orientation (unit quaternion, 4) from a feature vector."""

    def __init__(self, in_features: int) -> None:
        super().__init__()
        self.position = nn.Linear(in_features, 3)
        self.orientation = nn.Linear(in_features, 4)
        # Start at the identity rotation so early training sees sensible quaternions.
        with torch.no_grad():
            self.orientation.bias.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0]))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.position(x), nn.functional.normalize(self.orientation(x), dim=1)


SAMPLED_IMAGES_PER_PASS = 256  # see PoseHead.images_per_pass
# Where a backbone's dropout can sit (backbone.dropout_variant); see
# relocfw.model.dropout_backbone.
DROPOUT_VARIANTS = ("head", "kendall", "all")


def dropout_variant_of(variant: str) -> str:
    """`variant` if it is one of DROPOUT_VARIANTS; ConfigError naming the option if not."""
    if variant not in DROPOUT_VARIANTS:
        raise ConfigError(
            f"dropout_variant must be one of {', '.join(DROPOUT_VARIANTS)}, got {variant!r}"
        )
    return variant


class PoseHead(nn.Module):
    """Pooled trunk features -> descriptor -> dropout -> pose.

    Args:
        in_features: channels of the pooled trunk output.
        feature_dim: descriptor length (paper: 2048).
        dropout: dropout before the regressor (paper: 0.5).
    """

    def __init__(self, in_features: int, feature_dim: int, dropout: float) -> None:
        super().__init__()
        self.descriptor = nn.Linear(in_features, feature_dim)
        self.dropout_rate = dropout
        self.regressor = PoseRegressor(feature_dim)
        # Most sample x image inputs one pass of the sampled layers takes (memory).
        self.images_per_pass = SAMPLED_IMAGES_PER_PASS

    def describe(self, pooled: torch.Tensor) -> torch.Tensor:
        """[n, C] pooled trunk features -> [n, D] descriptors (no dropout, no pose)."""
        return torch.relu(self.descriptor(pooled))

    def forward(
        self,
        pooled: torch.Tensor,
        to_world: Callable[[torch.Tensor], torch.Tensor],
        mc_samples: int = 0,
    ) -> PoseOutput:
        features = self.describe(pooled)
        if self.training or mc_samples <= 0:
            dropped = nn.functional.dropout(features, self.dropout_rate, self.training)
            positions, quaternions = self.regressor(dropped)
            return PoseOutput(to_world(positions), quaternions, features)
        # All masks in one batch: [S * B, D].
        repeated = features.unsqueeze(0).expand(mc_samples, -1, -1).reshape(-1, features.shape[1])
        return self.sampled(repeated, features, to_world, mc_samples)

    def sampled_above(
        self,
        below: torch.Tensor,
        above: Callable[[torch.Tensor], torch.Tensor],
        clean: torch.Tensor,
        to_world: Callable[[torch.Tensor], torch.Tensor],
        mc_samples: int,
    ) -> PoseOutput:
        """Monte Carlo answers when dropout also sits below the descriptor.

        Args:
            below: [B, ...] what the layers under the first dropout gave, computed
                once per image: only `above` runs once per sample.
            above: the layers from the first dropout up to the pooled [n, C] trunk
                features, dropout on.
            clean: [B, C] the same pooled features with no dropout: the descriptor
                the index sees.
        """
        per_pass = max(1, self.images_per_pass // len(below))
        descriptors = []
        for start in range(0, mc_samples, per_pass):
            count = min(per_pass, mc_samples - start)
            repeated = below.repeat(count, *([1] * (below.dim() - 1)))  # sample-major
            descriptors.append(self.describe(above(repeated)))
        return self.sampled(torch.cat(descriptors), self.describe(clean), to_world, mc_samples)

    def sampled(
        self,
        descriptors: torch.Tensor,
        features: torch.Tensor,
        to_world: Callable[[torch.Tensor], torch.Tensor],
        mc_samples: int,
    ) -> PoseOutput:
        """Monte Carlo answers from per-sample descriptors.

        Args:
            descriptors: [S * B, D], sample-major: the descriptors of S samples of a
                batch of B (identical copies when only this head's dropout samples;
                different when dropout below the descriptor sampled them too).
            features: [B, D] the dropout-free descriptors, for the similarity index.

        Returns:
            The mean pose of the samples, with their position spread (m, sqrt of the
            trace of the covariance) and orientation spread (deg, mean angle from the
            mean rotation).
        """
        batch = len(features)
        dropped = nn.functional.dropout(descriptors, self.dropout_rate, training=True)
        positions, quaternions = self.regressor(dropped)
        positions = to_world(positions).view(mc_samples, batch, 3)
        quaternions = quaternions.view(mc_samples, batch, 4)
        mean_position, mean_quaternion, position_spread, angular_spread = sample_statistics(
            positions, quaternions
        )
        return PoseOutput(
            mean_position,
            mean_quaternion,
            features,
            position_spread=position_spread,
            orientation_spread_deg=angular_spread,
        )
