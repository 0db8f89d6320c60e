"""Hourglass pose network: encoder, up-convolutional decoder with skips, PoseNet's head.

After Melekhov, Ylioinas, Kannala and Rahtu, "Image-based Localization using Hourglass
Networks" (ICCV Workshops 2017): an ImageNet-pretrained encoder, a decoder of
up-convolutions that brings the deepest maps back up to a finer resolution, joined at
each step with the encoder's maps of that resolution (skip connections), so the pose
regressor sees fine-grained detail as well as the encoder's context. Here:

- encoder: the EfficientNet-Lite0 trunk of backbone=efficientnet_lite0, with its
  packaged ImageNet weights, ending with its 1280-channel head convolution (stride 32).
  Skips are taken where a resolution stage ends: MBConv blocks 2 (stride 4, 24
  channels), 4 (stride 8, 40) and 10 (stride 16, 112);
- decoder: three up-convolutions (ConvTranspose2d 4x4, stride 2, BatchNorm, ReLU),
  stride 32 -> 16 -> 8 -> 4, each output concatenated with the skip of its resolution;
  `decoder_channels` (default 256, 128, 64) are the up-convolutions' widths, so the
  last map has 64 + 24 = 88 channels at a quarter of the input's resolution;
- regressor: relocfw's PoseHead (2048-d descriptor, dropout, position and quaternion)
  on the global average of the last decoder map; the descriptor feeds the map.

Where this differs from the paper, and why. The paper's full text could not be read
where this was written, only its abstract ("a chain of convolution and up-convolution
layers followed by a regression part"; the up-convolutions "preserve the fine-grained
information of the input image"); the points marked (unchecked) follow that and the
usual hourglass design, and should be checked against the paper before results are
quoted as its architecture.

- Encoder: the paper's is ResNet34 (stages of 64, 128, 256, 512 channels). The only
  ImageNet weights that ship offline with relocfw are EfficientNet-Lite0's, so that is
  the encoder; its stages end at the same strides (4, 8, 16, 32), with other widths.
- Decoder (unchecked): one up-convolution per resolution stage above the finest, so
  three, back to stride 4, each followed by BatchNorm and ReLU (as the paper's
  decoder is described); the 4x4 kernel is chosen here, and the default widths mirror
  ResNet34's stages.
- Join (unchecked): concatenation, as in U-Net. It keeps each skip's maps unchanged
  and lets the decoder's widths differ from EfficientNet's narrow stages (24, 40, 112
  channels); a sum would tie every up-convolution's width to the stage it meets.
- Regressor: global average pooling into PoseHead, as every relocfw backbone does, so
  the layer before the regressor is the descriptor the k-means map and
  `query.scoring=shared` use; the paper's regression part is its own.
- Input size: any. The paper uses 224 x 224 crops; the presets use 96. Sizes that are
  not a multiple of 32 (and shared scoring's strips, of any width) work: the encoder
  halves sizes rounding down, so an up-convolution's output can be one cell larger than
  its skip and is resized to the skip's size (bilinearly) before they are joined.
- Dropout: `dropout_variant` as on EfficientNet-Lite0 (head, kendall, all); for "all"
  a dropout follows every encoder block (the first too: on trunk_lower's output), the
  head convolution and
  every decoder stage. The paper samples no dropout at test time.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from relocfw.core.errors import ConfigError
from relocfw.core.options import integer_at_least
from relocfw.model.dropout_backbone import Drop, DropoutBackbone, Maps
from relocfw.model.pose_head import PoseHead
from relocfw.plugins.efficientnet_lite import (
    EfficientNetLite0,
    lite_pixels,
    run_block,
    stem_and_first_block,
)

# The up-convolutions' widths: ResNet34's stage widths below its deepest (512), the
# decoder the paper's symmetric hourglass would have.
DECODER_CHANNELS = (256, 128, 64)


def encoder_trunk(input_size: int, pretrained: bool) -> nn.Module:
    """EfficientNet-Lite0's trunk, loaded exactly as backbone=efficientnet_lite0 loads it
    (ImageNet weights from the installed package when `pretrained`)."""
    try:
        # A one-wide head: only the trunk is kept, so its discarded head costs nothing.
        donor = EfficientNetLite0(input_size, feature_dim=1, dropout=0.0, pretrained=pretrained)
    except ConfigError as error:
        raise ConfigError(f"backbone=hourglass encodes with EfficientNet-Lite0: {error}") from error
    trunk = donor.trunk
    # ImageNet's classifier never runs here: 1.28M parameters kept out of model files.
    trunk._fc = nn.Identity()
    return trunk


def stage_ends(trunk: nn.Module) -> tuple[int, ...]:
    """Indices of the MBConv blocks after which the resolution halves (the next block
    has stride 2): the last block of each resolution stage but the deepest. For
    EfficientNet-Lite0: 0 (stride 2), 2 (4), 4 (8) and 10 (16)."""
    blocks = trunk._blocks
    return tuple(
        index
        for index in range(len(blocks) - 1)
        if max(blocks[index + 1]._depthwise_conv.stride) == 2
    )


def decoder_widths(channels: Sequence[int]) -> tuple[int, int, int]:
    """`channels` as three positive ints, or a ConfigError naming the option."""
    if isinstance(channels, str) or not hasattr(channels, "__len__") or len(channels) != 3:
        raise ConfigError(
            "decoder_channels must list 3 widths, one per up-convolution "
            f"(strides 16, 8, 4), got {channels!r}"
        )
    first, second, third = (
        integer_at_least(f"decoder_channels[{i}]", value, 1) for i, value in enumerate(channels)
    )
    return first, second, third


class UpStage(nn.Module):
    """One decoder step: up-convolution x2 (BatchNorm, ReLU), then the skip joins.

    Args:
        in_channels: channels of the coarser map coming up.
        out_channels: the up-convolution's width.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        # Kernel 4 at stride 2 covers every output cell with the same number of taps
        # (no checkerboard pattern from uneven overlap) and exactly doubles the size.
        self.up = nn.Sequential(
            nn.ConvTranspose2d(in_channels, out_channels, 4, stride=2, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
        )

    def forward(self, coarse: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        """[n, C_in, h, w] and the encoder's [n, C_skip, H, W] (H = 2h or 2h - 1) ->
        [n, out_channels + C_skip, H, W]."""
        up = self.up(coarse)
        # When exporting (ONNX, traced or through torch.export) always resize: the graph
        # must serve every size, and a resize to the same size is exact (bilinear
        # weights 1 and 0).
        exporting = torch.jit.is_tracing() or torch.compiler.is_exporting()
        if exporting or up.shape[-2:] != skip.shape[-2:]:
            up = nn.functional.interpolate(
                up, size=skip.shape[-2:], mode="bilinear", align_corners=False
            )
        return torch.cat((up, skip), dim=1)


class Hourglass(DropoutBackbone):
    """EfficientNet-Lite0 encoder -> up-convolutional decoder with skips -> pose.

    Args:
        input_size: square network input (paper: 224).
        feature_dim: descriptor length.
        dropout: dropout before the regressor (and where `dropout_variant` puts it).
        pretrained: start the encoder from the packaged ImageNet weights; the decoder
            and the head always start from random weights.
        mc_samples: Monte Carlo dropout samples at test time (0: off).
        dropout_variant: "head", "kendall" (also on the last decoder map, before the
            pool) or "all" (after every encoder block, the first included, the encoder's
            head convolution and every decoder stage); the stem and the first block
            run once per query when sampling.
        decoder_channels: the three up-convolutions' widths, deepest first.
    """

    rebuild_overrides = {"pretrained": False}
    # As backbone=efficientnet_lite0: head is the variant without a key entry.
    key_defaults = {"dropout_variant": "head"}

    def __init__(
        self,
        input_size: int = 224,
        feature_dim: int = 2048,
        dropout: float = 0.5,
        pretrained: bool = True,
        mc_samples: int = 0,
        dropout_variant: str = "head",
        decoder_channels: Sequence[int] = DECODER_CHANNELS,
    ) -> None:
        super().__init__(input_size, feature_dim, dropout, mc_samples, dropout_variant)
        self.decoder_channels = decoder_widths(decoder_channels)
        self.pretrained = bool(pretrained)
        self.trunk = encoder_trunk(self.input_size, self.pretrained)
        ends = stage_ends(self.trunk)
        # Block 0 ends the stride-2 stage inside trunk_lower; the decoder stops at stride 4.
        self.skip_blocks = ends[1:]
        skip_widths = [self.trunk._blocks[i]._bn2.num_features for i in self.skip_blocks]
        coarse = self.trunk._conv_head.out_channels
        stages = []
        # Deepest first: each stage meets the skip of the next finer stride.
        for width, skip in zip(self.decoder_channels, reversed(skip_widths), strict=True):
            stages.append(UpStage(coarse, width))
            coarse = width + skip
        self.decoder = nn.ModuleList(stages)
        self.head = PoseHead(coarse, self.feature_dim, self.dropout_rate)

    def normalise(self, images: torch.Tensor) -> torch.Tensor:
        return lite_pixels(images)  # the encoder's own input range

    def trunk_lower(self, x: torch.Tensor) -> torch.Tensor:
        """Stem and the first MBConv block: below every place a dropout can sit."""
        return stem_and_first_block(self.trunk, x)

    def trunk_upper(self, below: torch.Tensor, drop: Drop | None = None) -> Maps:
        """The decoder's maps, coarsest first (strides 16, 8, 4); the last is pooled."""
        return self.decoder_maps(self.encoder_maps(below, drop), drop)

    def encoder_maps(self, below: torch.Tensor, drop: Drop | None = None) -> Maps:
        """The skips (strides 4, 8, 16) and the deepest map (the head convolution's,
        stride 32), from `trunk_lower`'s output; `drop` on that and after each block."""
        d = drop or (lambda t: t)
        x = d(below)
        skips = []
        for index in range(1, len(self.trunk._blocks)):
            x = d(self.block(index, x))
            if index in self.skip_blocks:
                skips.append(x)  # dropped as the block's output is: one map, two uses
        deepest = d(self.trunk._swish(self.trunk._bn1(self.trunk._conv_head(x))))
        return (*skips, deepest)

    def decoder_maps(self, encoder: Maps, drop: Drop | None = None) -> Maps:
        """Each decoder stage's joined map from `encoder_maps`, `drop` after each."""
        d = drop or (lambda t: t)
        *skips, x = encoder
        maps = []
        for stage, skip in zip(self.decoder, reversed(skips), strict=True):
            x = d(stage(x, skip))
            maps.append(x)
        return tuple(maps)

    def block(self, index: int, x: torch.Tensor) -> torch.Tensor:
        return run_block(self.trunk, index, x)  # as backbone=efficientnet_lite0 runs it
