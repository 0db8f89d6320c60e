"""Counting a network's work in multiply-adds, to report costs that do not depend on
the machine (relocfw.core.sampling.sample_share)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import nn


def layer_multiply_adds(
    layer: nn.Module, output: torch.Tensor, source: torch.Tensor | None = None
) -> int:
    """Multiply-adds a convolution or linear layer made to produce `output` from
    `source` (0 for any other layer: activations, pooling, normalisation and dropout
    are a small share of a CNN's work and are not counted).

    A transposed convolution (a decoder's up-convolution, backbone=hourglass) spreads
    each input cell over its kernel: its work is counted from `source`, its input.
    """
    if isinstance(layer, (nn.ConvTranspose1d, nn.ConvTranspose2d, nn.ConvTranspose3d)):
        if source is None:
            raise ValueError(f"{type(layer).__name__}'s multiply-adds need its input")
        per_input = layer.out_channels // layer.groups * math.prod(layer.kernel_size)
        return source.numel() * per_input
    if isinstance(layer, (nn.Conv1d, nn.Conv2d, nn.Conv3d)):
        per_output = layer.in_channels // layer.groups * math.prod(layer.kernel_size)
        return output.numel() * per_output
    if isinstance(layer, nn.Linear):
        return output.numel() * layer.in_features
    return 0


def multiply_adds_by_layer(network: nn.Module, run: Callable[[], Any]) -> dict[nn.Module, int]:
    """Multiply-adds of each of `network`'s convolutions and linear layers while
    `run()` runs (layers that did no counted work are left out).

    Counted by forward hooks, so layers run twice (e.g. once per Monte Carlo sample)
    count twice, and layers that do not run count nothing.
    """
    counts: dict[nn.Module, int] = {}

    def count(layer: nn.Module, inputs: Any, output: Any) -> None:
        if isinstance(output, torch.Tensor):
            source = inputs[0] if inputs and isinstance(inputs[0], torch.Tensor) else None
            work = layer_multiply_adds(layer, output, source)
            if work:
                counts[layer] = counts.get(layer, 0) + work

    hooks = [layer.register_forward_hook(count) for layer in network.modules()]
    try:
        run()
    finally:
        for hook in hooks:
            hook.remove()
    return counts


def multiply_adds(network: nn.Module, run: Callable[[], Any]) -> int:
    """Multiply-adds of `network`'s convolutions and linear layers while `run()` runs
    (`multiply_adds_by_layer`, summed)."""
    return sum(multiply_adds_by_layer(network, run).values())
