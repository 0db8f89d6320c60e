"""The scene-coordinate head: per-cell encoder features -> the world point seen there.

ACE's arrangement (Brachmann et al., CVPR 2023) in a small form: 1x1 convolutions, i.e.
the same MLP on every cell's feature vector, here written as Linear layers over
[N, C] rows (the buffer holds cells, not images). Its output is an offset from the
scene's mean point, so a freshly initialised head predicts the scene's centre and
every layer's output stays near unit scale; the input is standardised per channel
with the buffer's statistics, so Adam's one learning rate suits every channel of a
frozen encoder whose channels differ in scale by orders of magnitude.

Everything the head needs at query time is in its state_dict (weights, the input
standardisation and the scene mean, as buffers), so a model file stores plain tensors.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from relocfw.core.options import integer_at_least


class SceneCoordinateHead(nn.Module):
    """MLP from a cell's encoder features to a world point.

    Args:
        channels: the encoder's feature channels (C).
        width: each hidden layer's width.
        layers: hidden layers (ReLU after each), >= 1.
    """

    def __init__(self, channels: int, width: int = 256, layers: int = 3) -> None:
        super().__init__()
        self.channels = integer_at_least("channels", channels, 1)
        self.width = integer_at_least("refine.head_width", width, 1)
        self.layers = integer_at_least("refine.head_layers", layers, 1)
        sizes = [self.channels] + [self.width] * self.layers
        self.hidden = nn.ModuleList(
            nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=True)
        )
        self.out = nn.Linear(self.width, 3)
        self.register_buffer("input_mean", torch.zeros(self.channels))
        self.register_buffer("input_std", torch.ones(self.channels))
        self.register_buffer("scene_mean", torch.zeros(3))

    def initialise(self, generator: torch.Generator) -> None:
        """Seeded initial weights (He-uniform for the ReLU layers, a small last
        layer so the first predictions sit near the scene mean), drawn from
        `generator` only: torch's global stream is neither read nor moved."""
        with torch.no_grad():
            for layer in self.hidden:
                bound = math.sqrt(6.0 / layer.in_features)
                layer.weight.uniform_(-bound, bound, generator=generator)
                layer.bias.zero_()
            bound = 0.1 / math.sqrt(self.out.in_features)
            self.out.weight.uniform_(-bound, bound, generator=generator)
            self.out.bias.zero_()

    def set_statistics(
        self, input_mean: torch.Tensor, input_std: torch.Tensor, scene_mean: torch.Tensor
    ) -> None:
        """The per-channel standardisation of the inputs and the scene's mean point."""
        with torch.no_grad():
            self.input_mean.copy_(input_mean)
            # A channel that never varies on the buffer (a dead unit) is divided by 1:
            # its z-score stays 0 rather than exploding on a query that lights it.
            self.input_std.copy_(torch.where(input_std > 1e-6, input_std, torch.ones(())))
            self.scene_mean.copy_(scene_mean)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """[N, C] features -> [N, 3] float32 world points."""
        x = (features.float() - self.input_mean) / self.input_std
        for layer in self.hidden:
            x = torch.relu(layer(x))
        return self.out(x) + self.scene_mean


def built_head(channels: int, width: int, layers: int) -> SceneCoordinateHead:
    """A head of these sizes, its layers' default initial draws kept off torch's global
    stream (`initialise` or loaded weights replace them)."""
    with torch.random.fork_rng(devices=[]):
        return SceneCoordinateHead(channels, width, layers)
