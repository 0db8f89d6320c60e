"""GoogLeNet (Inception v1) trunk, with torchvision's module names.

Module names match torchvision's `googlenet` state_dict so ImageNet weights load by
name (see `posenet.load_imagenet_weights`). Like torchvision, convolutions carry batch
normalisation instead of the original local response normalisation; it is what makes
training from scratch on a few hundred images work at all.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

# (in, 1x1, 3x3 reduce, 3x3, 5x5 reduce, 5x5, pool proj) for each inception block.
INCEPTION_CHANNELS = {
    "inception3a": (192, 64, 96, 128, 16, 32, 32),
    "inception3b": (256, 128, 128, 192, 32, 96, 64),
    "inception4a": (480, 192, 96, 208, 16, 48, 64),
    "inception4b": (512, 160, 112, 224, 24, 64, 64),
    "inception4c": (512, 128, 128, 256, 24, 64, 64),
    "inception4d": (512, 112, 144, 288, 32, 64, 64),
    "inception4e": (528, 256, 160, 320, 32, 128, 128),
    "inception5a": (832, 256, 160, 320, 32, 128, 128),
    "inception5b": (832, 384, 192, 384, 48, 128, 128),
}


def scaled(channels: int, width: float) -> int:
    """Channel count under a width multiplier (tiny networks for fast tests)."""
    return max(4, round(channels * width))


class ConvBnRelu(nn.Module):
    """torchvision's BasicConv2d: convolution without bias, batch norm, ReLU."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, **kwargs) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size, bias=False, **kwargs)
        self.bn = nn.BatchNorm2d(out_channels, eps=0.001)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.bn(self.conv(x)))


class Inception(nn.Module):
    """Four parallel branches concatenated along channels."""

    def __init__(self, c_in: int, channels: tuple[int, ...], width: float) -> None:
        super().__init__()
        c1, c3r, c3, c5r, c5, cp = (scaled(c, width) for c in channels[1:])
        self.out_channels = c1 + c3 + c5 + cp
        self.branch1 = ConvBnRelu(c_in, c1, 1)
        self.branch2 = nn.Sequential(ConvBnRelu(c_in, c3r, 1), ConvBnRelu(c3r, c3, 3, padding=1))
        # torchvision uses 3x3 here where the paper says 5x5; kept for weight compatibility.
        self.branch3 = nn.Sequential(ConvBnRelu(c_in, c5r, 1), ConvBnRelu(c5r, c5, 3, padding=1))
        self.branch4 = nn.Sequential(
            nn.MaxPool2d(3, stride=1, padding=1, ceil_mode=True), ConvBnRelu(c_in, cp, 1)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.branch1(x), self.branch2(x), self.branch3(x), self.branch4(x)], 1)


class GoogLeNetTrunk(nn.Module):
    """Stem and inception blocks; returns the 4a, 4d and 5b feature maps.

    4a and 4d feed PoseNet's two auxiliary heads, 5b the main head.
    """

    def __init__(self, width: float = 1.0) -> None:
        super().__init__()
        self.conv1 = ConvBnRelu(3, scaled(64, width), 7, stride=2, padding=3)
        self.maxpool1 = nn.MaxPool2d(3, stride=2, ceil_mode=True)
        self.conv2 = ConvBnRelu(scaled(64, width), scaled(64, width), 1)
        self.conv3 = ConvBnRelu(scaled(64, width), scaled(192, width), 3, padding=1)
        self.maxpool2 = nn.MaxPool2d(3, stride=2, ceil_mode=True)
        # Each block takes what the previous one gives: under a width multiplier the
        # rounded branch widths need not add up to the scaled nominal input.
        c_in = scaled(192, width)
        for name, channels in INCEPTION_CHANNELS.items():
            block = Inception(c_in, channels, width)
            setattr(self, name, block)
            c_in = block.out_channels
        self.maxpool3 = nn.MaxPool2d(3, stride=2, ceil_mode=True)
        self.maxpool4 = nn.MaxPool2d(2, stride=2, ceil_mode=True)
        self.aux_channels = (self.inception4a.out_channels, self.inception4d.out_channels)
        self.out_channels = self.inception5b.out_channels

    def forward(
        self, x: torch.Tensor, drop: Callable[[torch.Tensor], torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The 4a, 4d and 5b maps; `drop`, if given, is applied after every inception
        block (Bayesian PoseNet's "all layers" dropout)."""
        return self.upper(self.lower(x), drop)

    def lower(self, x: torch.Tensor) -> torch.Tensor:
        """Stem and inception 3a: everything below the first place a dropout can sit,
        so Monte Carlo sampling runs it once per query, not once per sample."""
        x = self.maxpool1(self.conv1(x))
        x = self.maxpool2(self.conv3(self.conv2(x)))
        return self.inception3a(x)

    def upper(
        self, at_3a: torch.Tensor, drop: Callable[[torch.Tensor], torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """From inception 3a's output to the 4a, 4d and 5b maps, `drop` after each block."""
        d = drop or (lambda t: t)
        x = self.maxpool3(d(self.inception3b(d(at_3a))))
        at_4a = d(self.inception4a(x))
        at_4d = d(self.inception4d(d(self.inception4c(d(self.inception4b(at_4a))))))
        x = self.maxpool4(d(self.inception4e(at_4d)))
        at_5b = d(self.inception5b(d(self.inception5a(x))))
        return at_4a, at_4d, at_5b
