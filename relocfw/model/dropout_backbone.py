"""A backbone with PoseNet's head and Bayesian PoseNet's three dropout placements.

Where Monte Carlo dropout samples (Bayesian PoseNet, Kendall & Cipolla 2016), the
`dropout_variant` option:

- head: only before the pose regressor (PoseNet's own dropout). The layers above it
  are linear, so the samples' mean is PoseNet's pose in expectation and the spread is
  a fixed function of the descriptor, not the model's doubt.
- kendall: the released Bayesian PoseNet: also on the trunk's last convolutional
  maps, before the average pool, so the samples differ in their descriptors.
- all: after every block of the trunk above its lowest one.

kendall and all drop in training too: they are different models (checkpoint key).
When sampling, the layers below the first dropout run once per query and the rest
once per sample, all samples batched (PoseHead.sampled_above).

A subclass builds its trunk and `self.head`, and says how its trunk splits:
`normalise` (the input normalisation its weights expect), `trunk_lower` (the layers
below every place a dropout can sit) and `trunk_upper` (the rest, with a dropout
after each block when asked); `training_output` adds what only training uses.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable

import torch
from torch import nn

from relocfw.core.errors import ConfigError
from relocfw.core.interfaces import Backbone
from relocfw.core.options import integer_at_least, probability
from relocfw.core.values import PoseOutput
from relocfw.model.pose_head import PoseHead, dropout_variant_of

Drop = Callable[[torch.Tensor], torch.Tensor]
Maps = tuple[torch.Tensor, ...]  # a trunk's maps, the last one pooled for the descriptor


def pool(maps: torch.Tensor) -> torch.Tensor:
    """[n, C, h, w] -> [n, C] global average."""
    return torch.flatten(nn.functional.adaptive_avg_pool2d(maps, 1), 1)


class DropoutBackbone(Backbone):
    """Trunk -> global average pool -> PoseHead, with dropout where `dropout_variant`
    puts it (see the module's docstring) and `mc_samples` Monte Carlo samples at test
    time (a test-time option: it does not change the trained model, so it is not part
    of the checkpoint's key).

    Sets the options it validates: `input_size`, `feature_dim`, `dropout_rate`,
    `dropout_variant` and `mc_samples`. The subclass then builds its modules, the
    trunk before `self.head` (their order is the order of their random initial
    weights and of the state_dict's keys).
    """

    test_time_options = ("mc_samples",)
    head: PoseHead

    def __init__(
        self,
        input_size: int,
        feature_dim: int,
        dropout: float,
        mc_samples: int,
        dropout_variant: str,
    ) -> None:
        super().__init__()
        self.input_size = integer_at_least("input_size", input_size, 32)
        self.feature_dim = integer_at_least("feature_dim", feature_dim, 1)
        if not 0 <= probability("dropout", dropout) < 1:
            raise ConfigError(f"dropout must be in [0, 1), got {dropout}")
        self.dropout_variant = dropout_variant_of(dropout_variant)
        self.dropout_rate = float(dropout)
        self.mc_samples = integer_at_least("mc_samples", mc_samples, 0)

    @abstractmethod
    def normalise(self, images: torch.Tensor) -> torch.Tensor:
        """RGB in [0, 1] -> the input the trunk's weights were trained on."""

    @abstractmethod
    def trunk_lower(self, x: torch.Tensor) -> torch.Tensor:
        """The layers below every place a dropout can sit: sampling runs them once."""

    @abstractmethod
    def trunk_upper(
        self, below: torch.Tensor, drop: Drop | None = None
    ) -> tuple[torch.Tensor, ...]:
        """The rest of the trunk from `trunk_lower`'s output, `drop` (if given) on that
        output and after each block. The last map is what the descriptor pools; any
        before it are for `training_output` (e.g. auxiliary heads)."""

    def trunk_maps(self, x: torch.Tensor, drop: Drop | None = None) -> Maps:
        """The whole trunk: `trunk_upper` on `trunk_lower`. A subclass whose trunk is
        one module may call that module instead, so hooks on it see every pass."""
        return self.trunk_upper(self.trunk_lower(x), drop)

    def training_output(self, output: PoseOutput, maps: Maps) -> PoseOutput:
        """The training-mode answer from the main head's `output` and the trunk's
        `maps`; a subclass with auxiliary heads adds theirs."""
        return output

    def forward(self, images: torch.Tensor) -> PoseOutput:
        if not self.training and self.mc_samples > 0:
            return self.monte_carlo_answer(images)
        x = self.normalise(images)
        drop = self.drop if self.training and self.dropout_variant == "all" else None
        maps = self.trunk_maps(x, drop)
        last = maps[-1]
        if self.training and self.dropout_variant == "kendall":
            last = self.drop(last)
        output = self.head(pool(last), self.to_world_positions, self.mc_samples)
        return self.training_output(output, maps) if self.training else output

    def drop(self, maps: torch.Tensor) -> torch.Tensor:
        """Dropout that is on whenever it is called (training, or sampling at test time)."""
        return nn.functional.dropout(maps, self.dropout_rate, training=True)

    def monte_carlo_answer(
        self,
        images: torch.Tensor,
        last_maps: Callable[[torch.Tensor], torch.Tensor] | None = None,
        lower_maps: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ) -> PoseOutput:
        """Eval-mode answers with `mc_samples` dropout masks per image: the layers
        below the first dropout run once for the batch, the rest once per sample,
        batched.

        Args:
            images: [B, 3, s, s] RGB in [0, 1].
            last_maps: images -> the trunk's last maps, dropout-free (default: this
                network's `feature_maps`); an inference engine passes its own graph.
            lower_maps: images -> `trunk_lower`'s output (default: this network's), for
                the "all" variant. The sampled layers always run here, in torch.
        """
        last_maps = last_maps or self.feature_maps
        if self.dropout_variant == "head":  # only the head samples
            return self.head(pool(last_maps(images)), self.to_world_positions, self.mc_samples)
        if self.dropout_variant == "kendall":
            below = last_maps(images)  # the first dropout is on it

            def above(maps: torch.Tensor) -> torch.Tensor:
                return pool(self.drop(maps))

            clean = pool(below)
        else:
            lower_maps = lower_maps or self.lower_maps
            below = lower_maps(images)  # a dropout follows it

            def above(maps: torch.Tensor) -> torch.Tensor:
                return pool(self.trunk_upper(maps, self.drop)[-1])

            clean = pool(self.trunk_upper(below)[-1])
        return self.head.sampled_above(
            below, above, clean, self.to_world_positions, self.mc_samples
        )

    def lower_maps(self, images: torch.Tensor) -> torch.Tensor:
        """`trunk_lower` of normalised `images`: what an engine exports for "all"."""
        return self.trunk_lower(self.normalise(images))

    def feature_maps(self, images: torch.Tensor) -> torch.Tensor:
        return self.trunk_maps(self.normalise(images))[-1]

    def describe_pooled(self, pooled: torch.Tensor) -> torch.Tensor:
        return self.head.describe(pooled)
