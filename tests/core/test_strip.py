"""The strip against the definition: crop the original image, then resize that crop.

The expected network input is computed from the crop in original pixels with OpenCV
alone; `Strip.window` only picks what is compared, never what it is compared with.
"""

import cv2
import numpy as np
import pytest

from relocfw.core.imaging import Strip
from relocfw.core.interfaces import crop_at, crop_side_and_span


def smooth_image(width: int, height: int) -> np.ndarray:
    """Slowly varying RGB content, different along x and y and in each channel."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    u, v = x / width, y / height
    red = 128 + 90 * np.sin(2 * np.pi * 1.0 * u) * np.cos(2 * np.pi * 0.7 * v)
    green = 128 + 100 * np.cos(2 * np.pi * 1.3 * (x + y) / (width + height))
    blue = 40 + 180 * u * v
    return np.clip(np.stack([red, green, blue], axis=-1), 0, 255).round().astype(np.uint8)


def crop_then_resize(image: np.ndarray, offset: int, size: int) -> np.ndarray:
    """The definition of a network input: the square crop at `offset`, resized."""
    height, width = image.shape[:2]
    crop = crop_at(offset, width, height)
    square = image[crop.y : crop.y + crop.size, crop.x : crop.x + crop.size]
    interpolation = cv2.INTER_AREA if crop.size > size else cv2.INTER_LINEAR
    return cv2.resize(square, (size, size), interpolation=interpolation).astype(np.float64)


def offsets(span: int) -> list[int]:
    """Both ends, their neighbours and points between."""
    return sorted({0, 1, span // 3, span // 2, (2 * span) // 3, span - 1, span})


SHAPES = [(400, 300), (300, 400), (1024, 768), (123, 77), (77, 123), (60, 40), (40, 60)]


@pytest.mark.parametrize("width, height", SHAPES, ids=[f"{w}x{h}" for w, h in SHAPES])
@pytest.mark.parametrize("size", [32, 48])
def test_strip_window_is_the_crop_resized(width, height, size):
    image = smooth_image(width, height)
    strip = Strip(image, size)
    _, span = crop_side_and_span(width, height)
    long_axis = 1 if width >= height else 0
    for offset in offsets(span):
        expected = crop_then_resize(image, offset, size)
        got = strip.cut(strip.window(crop_at(offset, width, height))).numpy()
        error = np.abs(got.transpose(1, 2, 0) - expected).mean()
        # How far the strip's window can sit from the true crop, in strip pixels: half
        # a pixel from rounding offset x scale to a whole corner, plus the strip's
        # length being rounded to whole pixels (off by at most half a pixel at its far
        # end, proportionally less before it, so at most 0.5 x end / length here).
        # A pixel of shift costs about `step` grey levels on this image (the mean
        # difference of neighbours along the long axis); the two resizes each round to
        # uint8 (0.5 each).
        step = np.abs(np.diff(expected, axis=long_axis)).mean()
        length = strip.pixels.shape[1 + long_axis]  # [3, H, W]
        end = offset * size / min(width, height) + size
        allowed = 1.0 + step * (0.5 + 0.5 * end / length)
        assert error <= allowed, f"offset {offset}: {error:.2f} grey levels off"
        assert error < 3.0  # and small in grey levels: the worst case here is 2.3


@pytest.mark.parametrize("width, height", [(400, 300), (300, 400)])
def test_a_window_two_pixels_off_is_clearly_worse(width, height):
    # What makes the tolerance above meaningful: a misplaced window fails it.
    image = smooth_image(width, height)
    strip = Strip(image, 32)
    _, span = crop_side_and_span(width, height)
    expected = crop_then_resize(image, span // 2, 32)
    y, x = strip.window(crop_at(span // 2, width, height))
    shifted = (y + 2, x) if height > width else (y, x + 2)
    right = np.abs(strip.cut((y, x)).numpy().transpose(1, 2, 0) - expected).mean()
    wrong = np.abs(strip.cut(shifted).numpy().transpose(1, 2, 0) - expected).mean()
    assert wrong > 3.0 > right


@pytest.mark.parametrize("width, height", [(400, 300), (300, 400), (77, 123)])
def test_the_strip_short_side_is_the_input_and_the_last_window_reaches_the_far_edge(width, height):
    strip = Strip(smooth_image(width, height), 32)
    short, long_ = sorted((width, height))
    along = strip.pixels.shape[1:] if height > width else strip.pixels.shape[1:][::-1]
    assert along[1] == 32 and along[0] == round(long_ * 32 / short)
    _, span = crop_side_and_span(width, height)
    y, x = strip.window(crop_at(span, width, height))
    assert (y if height > width else x) + 32 == along[0]
    assert (x if height > width else y) == 0


@pytest.mark.parametrize("width, height", [(400, 300), (300, 400)])
def test_with_a_crop_scale_the_window_is_the_centre_of_the_crop_resized(width, height):
    # A model trained on PoseNet's crops (crop_scale 256/224) sees the central
    # 224/256 of each crop at query time: crop, keep its centre, resize.
    image = smooth_image(width, height)
    strip = Strip(image, 56, crop_scale=256 / 224)  # 56 x 256/224 = 64: no rounding
    _, span = crop_side_and_span(width, height)
    for offset in (0, span // 2, span):
        crop = crop_at(offset, width, height)
        inner = round(crop.size * 224 / 256)
        start = (crop.size - inner) // 2
        square = image[crop.y : crop.y + crop.size, crop.x : crop.x + crop.size]
        centre = square[start : start + inner, start : start + inner]
        expected = cv2.resize(centre, (56, 56), interpolation=cv2.INTER_AREA).astype(float)
        got = strip.cut(strip.window(crop)).numpy().transpose(1, 2, 0)
        error = np.abs(got - expected).mean()
        assert error < 3.0, f"offset {offset}: {error:.2f} grey levels off"
        # The whole crop resized (what crop_scale 1 shows) is clearly something else.
        whole = crop_then_resize(image, offset, 56)
        assert np.abs(got - whole).mean() > 2 * error
