"""PoseNet: GoogLeNet trunk, two auxiliary pose heads and a main head.

The main head's 2048-d fully connected layer is the image descriptor used by the
similarity index. `weights=FILE` loads an ImageNet GoogLeNet state_dict saved from
torchvision (`torch.save(googlenet(weights=...).state_dict(), FILE)`), for transfer
learning; nothing is downloaded at run time.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch
from torch import nn

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import real_number
from relocfw.core.values import PoseOutput
from relocfw.model.checkpoints import read_torch_file
from relocfw.model.dropout_backbone import Drop, DropoutBackbone, Maps
from relocfw.model.dropout_backbone import pool as pool  # its old path, plugins.posenet.pool
from relocfw.model.pose_head import PoseHead, PoseRegressor
from relocfw.plugins.googlenet import ConvBnRelu, GoogLeNetTrunk, scaled

# Input normalisation of a network trained here from scratch: ImageNet's statistics.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
# torchvision's ImageNet GoogLeNet was trained on (x - 0.5) / 0.5 (its `transform_input`
# turns ImageNet-normalised input back into that), so its weights expect exactly that.
TORCHVISION_GOOGLENET_MEAN = (0.5, 0.5, 0.5)
TORCHVISION_GOOGLENET_STD = (0.5, 0.5, 0.5)
# torchvision modules with no counterpart here: the ImageNet classifiers.
DROPPED_PREFIXES = ("fc.", "aux1.fc2.", "aux2.fc2.")


class AuxiliaryHead(nn.Module):
    """PoseNet's auxiliary regressor on an intermediate feature map (torchvision names)."""

    def __init__(self, in_channels: int, width: float) -> None:
        super().__init__()
        self.conv = ConvBnRelu(in_channels, scaled(128, width), 1)
        self.fc1 = nn.Linear(scaled(128, width) * 16, scaled(1024, width))
        self.dropout = nn.Dropout(0.7)
        self.pose = PoseRegressor(scaled(1024, width))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.conv(nn.functional.adaptive_avg_pool2d(x, 4))
        return self.pose(self.dropout(torch.relu(self.fc1(torch.flatten(x, 1)))))


class PoseNet(DropoutBackbone):
    """GoogLeNet PoseNet (Kendall et al. 2015) with a 2048-d descriptor layer.

    Args:
        input_size: side of the square network input in pixels (paper: 224).
        feature_dim: length of the descriptor layer (paper: 2048).
        width: channel multiplier; 1.0 is GoogLeNet, smaller only for quick tests.
        dropout: dropout before the main pose regressor (paper: 0.5).
        weights: optional torchvision GoogLeNet ImageNet state_dict file.
        mc_samples: Monte Carlo dropout samples at test time (Bayesian PoseNet,
            Kendall & Cipolla 2016); 0 turns sampling off. A test-time option: it does
            not change the trained model, so it is not part of the checkpoint's key.
        dropout_variant: where dropout sits, in training and when sampling: "head"
            (before the regressor only), "kendall" (also on inception 5b's output) or
            "all" (after every inception block); see relocfw.model.dropout_backbone.
            The layers below the first dropout (the stem and inception 3a) run once
            per query, the rest once per sample, all samples batched.
    """

    rebuild_overrides = {"weights": None}

    def __init__(
        self,
        input_size: int = 224,
        feature_dim: int = 2048,
        width: float = 1.0,
        dropout: float = 0.5,
        weights: str | None = None,
        mc_samples: int = 0,
        dropout_variant: str = "head",
    ) -> None:
        super().__init__(input_size, feature_dim, dropout, mc_samples, dropout_variant)
        width = real_number("width", width)
        if not 0 < width <= 4:
            raise ConfigError(f"width must be in (0, 4], got {width}")
        self.trunk = GoogLeNetTrunk(width)
        self.aux1 = AuxiliaryHead(self.trunk.aux_channels[0], width)
        self.aux2 = AuxiliaryHead(self.trunk.aux_channels[1], width)
        self.head = PoseHead(self.trunk.out_channels, self.feature_dim, self.dropout_rate)
        self.pretrained = bool(weights)
        # Persistent: the normalisation belongs to the weights, so it travels with every
        # checkpoint and model file (a rebuilt model never reloads the weights file).
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1))
        if weights:
            if width != 1.0:
                raise ConfigError("backbone.weights needs width=1.0 (ImageNet GoogLeNet)")
            load_imagenet_weights(self, Path(weights))

    def normalise(self, images: torch.Tensor) -> torch.Tensor:
        return (images - self.mean) / self.std

    def trunk_lower(self, x: torch.Tensor) -> torch.Tensor:
        return self.trunk.lower(x)  # the stem and inception 3a

    def trunk_upper(self, below: torch.Tensor, drop: Drop | None = None) -> Maps:
        return self.trunk.upper(below, drop)  # inception 4a's, 4d's and 5b's maps

    def trunk_maps(self, x: torch.Tensor, drop: Drop | None = None) -> Maps:
        return self.trunk(x, drop)  # the module, so hooks on the trunk see the pass

    def training_output(self, output: PoseOutput, maps: Maps) -> PoseOutput:
        at_4a, at_4d, _ = maps
        auxiliary = tuple(
            (self.to_world_positions(p), q) for p, q in (self.aux1(at_4a), self.aux2(at_4d))
        )
        return dataclasses.replace(output, auxiliary=auxiliary)


def torchvision_to_posenet_key(key: str) -> str | None:
    """Name in PoseNet of a torchvision GoogLeNet parameter, or None if it has none."""
    if key.startswith(DROPPED_PREFIXES):
        return None
    if key.startswith(("aux1.", "aux2.")):
        return key
    return "trunk." + key


def load_imagenet_weights(model: PoseNet, path: Path) -> None:
    """Copy a torchvision GoogLeNet state_dict into the trunk and auxiliary layers, and
    switch the input normalisation to the (x - 0.5) / 0.5 those weights were trained on.

    Every trunk parameter must be provided with the right shape; anything missing is a
    wrong file, not something to start from random silently.
    """
    state = read_torch_file(path, "backbone.weights")
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise DataError(f"backbone.weights: {path} does not hold a state_dict")
    ours = model.state_dict()
    mapped = {}
    for key, value in state.items():
        target = torchvision_to_posenet_key(key)
        if target is None:
            continue
        if target not in ours:
            raise DataError(f"backbone.weights: {path}: unexpected key {key!r}")
        if ours[target].shape != value.shape:
            raise DataError(
                f"backbone.weights: {path}: {key!r} has shape {tuple(value.shape)}, "
                f"expected {tuple(ours[target].shape)}"
            )
        mapped[target] = value
    missing = [k for k in ours if k.startswith("trunk.") and k not in mapped]
    if missing:
        raise DataError(
            f"backbone.weights: {path} lacks {len(missing)} GoogLeNet parameters, "
            f"e.g. {missing[0]!r} (expected torchvision's googlenet key layout)"
        )
    model.load_state_dict(mapped, strict=False)
    with torch.no_grad():
        model.mean.copy_(torch.tensor(TORCHVISION_GOOGLENET_MEAN).view(1, 3, 1, 1))
        model.std.copy_(torch.tensor(TORCHVISION_GOOGLENET_STD).view(1, 3, 1, 1))
