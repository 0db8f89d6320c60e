"""Images as an encoder sees them for scene-coordinate regression, and its cells' pixels.

A stride-8 encoder gives one feature vector per cell of 8 x 8 encoder pixels. The
head predicts the world point seen at each cell's centre, so a cell must name a pixel
of the ORIGINAL image (where the camera's intrinsics hold): the centre of the cell in
the resized image, mapped back edge on edge as relocfw.core.camera.scaled_to does.
The pixel is a definition, not a measurement: training targets (depth read at it, or
its reprojection) and queries (PnP at it) use the same one, so the head learns the
point seen there whatever the encoder's true receptive-field centre is.

Encoder images are resized so both sides are multiples of CELL_MULTIPLE (16): the
stride-16 maps are then exactly half the stride-8 grid, and upsampled stride-16
features land on the stride-8 cells without a fractional offset.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from relocfw.core.errors import ConfigError

STRIDE = 8  # encoder pixels per cell side
CELL_MULTIPLE = 16  # both encoder sides are multiples of this (stride 16 halves stride 8)


@dataclass(frozen=True)
class Jitter:
    """One augmented encoder pass: the image's scale and its pixel gain and offset.

    Attributes:
        scale: the encoder image's shorter side is the refiner's size times this.
        gain: pixel values are multiplied by it (brightness and contrast together).
        offset: then this is added, in [0, 1] pixel units.
    """

    scale: float = 1.0
    gain: float = 1.0
    offset: float = 0.0


PLAIN = Jitter()


def encoder_size(width: int, height: int, short_side: int) -> tuple[int, int]:
    """(width, height) of the encoder image: the shorter side near `short_side`, the
    aspect kept, each side rounded to a multiple of CELL_MULTIPLE (at least one)."""
    if short_side < CELL_MULTIPLE:
        raise ConfigError(
            f"refine.image_size must be at least {CELL_MULTIPLE} pixels, got {short_side}"
        )
    scale = short_side / min(width, height)

    def rounded(side: int) -> int:
        return max(CELL_MULTIPLE, int(round(side * scale / CELL_MULTIPLE)) * CELL_MULTIPLE)

    return rounded(width), rounded(height)


def encoder_input(
    image: np.ndarray, short_side: int, jitter: Jitter = PLAIN
) -> tuple[torch.Tensor, tuple[float, float]]:
    """The image resized for the encoder, as [1, 3, h, w] float32 in [0, 1], and the
    (x, y) factors from encoder pixels to the image's pixels.

    Args:
        image: [H, W, 3] uint8 RGB (checked by the caller).
        short_side: the encoder image's shorter side before rounding (refine.image_size).
        jitter: scale, gain and offset of an augmented pass (PLAIN: none).
    """
    height, width = image.shape[:2]
    side = max(CELL_MULTIPLE, int(round(short_side * jitter.scale)))
    new_width, new_height = encoder_size(width, height, side)
    # INTER_AREA when shrinking: averaging avoids the aliasing a query never shows.
    shrink = new_width < width
    resized = cv2.resize(
        image,
        (new_width, new_height),
        interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR,
    )
    pixels = torch.from_numpy(resized).permute(2, 0, 1).float().div_(255.0)
    if jitter.gain != 1.0 or jitter.offset != 0.0:
        pixels = (pixels * jitter.gain + jitter.offset).clamp_(0.0, 1.0)
    return pixels[None], (width / new_width, height / new_height)


def cell_pixels(rows: int, columns: int, factors: tuple[float, float]) -> np.ndarray:
    """[rows * columns, 2] float64 pixel (x, y) in the original image of each cell's
    centre, row by row (the order of a [C, rows, columns] map flattened)."""
    # The centre of cell j spans encoder pixels [8j, 8j + 8): 8j + 3.5 from the
    # top-left pixel's centre; then edge on edge into the original image.
    x = (np.arange(columns) * STRIDE + (STRIDE - 1) / 2 + 0.5) * factors[0] - 0.5
    y = (np.arange(rows) * STRIDE + (STRIDE - 1) / 2 + 0.5) * factors[1] - 0.5
    grid_x, grid_y = np.meshgrid(x, y)
    return np.column_stack([grid_x.ravel(), grid_y.ravel()])


def random_jitter(
    rng: np.random.Generator, scale_jitter: float, brightness_jitter: float
) -> Jitter:
    """A jitter drawn from `rng`: the scale log-uniform in [1/(1+s), 1+s], the gain
    uniform in [1-b, 1+b] and the offset uniform in [-b/2, b/2]."""
    spread = np.log1p(scale_jitter)
    return Jitter(
        scale=float(np.exp(rng.uniform(-spread, spread))),
        gain=float(rng.uniform(1.0 - brightness_jitter, 1.0 + brightness_jitter)),
        offset=float(rng.uniform(-brightness_jitter / 2, brightness_jitter / 2)),
    )
