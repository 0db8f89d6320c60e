"""The request body: an encoded PNG or JPEG, checked before and after decoding.

The checks are relocfw.core.imaging's, which `task=localize` runs on files (the
header's announced size, a 16-bit grey PNG refused as a depth map, OpenCV's colour
decoding: 16-bit colour scaled to 8 bits, alpha dropped), plus what a service needs
on top: only PNG and JPEG (the two formats whose headers are read before decoding,
so no other format can announce a decompression bomb), a tighter pixel limit
(serve.max_pixels) and a JPEG refused when its end marker is missing (OpenCV decodes
such a file with its missing rows grey and only a warning on stderr).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from relocfw.core.errors import DataError
from relocfw.core.imaging import (
    PNG_SIGNATURE,
    announced_size,
    check_announced_size,
    is_16_bit_grey_png,
)

# How the imaging checks name what they read: the body, never a path.
BODY = Path("the request body")
JPEG_START = b"\xff\xd8"
JPEG_END = b"\xff\xd9"


class MediaTypeError(DataError):
    """The request's Content-Type is not an image type (answered 415)."""


def check_content_type(content_type: str | None) -> None:
    """An `image/*` Content-Type (parameters allowed), or MediaTypeError."""
    media = (content_type or "").split(";", 1)[0].strip().lower()
    if not media.startswith("image/"):
        raise MediaTypeError(
            f"Content-Type must be image/png or image/jpeg (the encoded image as the "
            f"body), got {content_type or 'none'!r}"
        )


def image_format(data: bytes) -> str:
    """ "png" or "jpeg" from the first bytes; DataError for anything else."""
    if data.startswith(PNG_SIGNATURE):
        return "png"
    if data.startswith(JPEG_START):
        return "jpeg"
    raise DataError("the request body is not a PNG or JPEG image (its first bytes are neither)")


def check_pixels(data: np.ndarray, max_pixels: int) -> None:
    """Refuse a header announcing more than imaging.MAX_IMAGE_PIXELS (imaging's own
    message) or more than `max_pixels` (serve.max_pixels), before decoding."""
    check_announced_size(data, BODY)
    size = announced_size(data)
    if size is None:
        raise DataError("the request body's image header is truncated or damaged (no size found)")
    if size[0] * size[1] > max_pixels:
        raise DataError(
            f"the request body's header announces {size[0]} x {size[1]} pixels, more than "
            f"the {max_pixels} this service decodes (serve.max_pixels); scale the image down"
        )


def decode_image(body: bytes, max_pixels: int) -> np.ndarray:
    """H x W x 3 uint8 RGB pixels of an encoded PNG or JPEG.

    Raises:
        DataError: one line saying what is wrong: an empty body, not a PNG or JPEG, a
            header announcing too many pixels, a 16-bit grey PNG (a depth map), a
            JPEG without its end marker (truncated), bytes OpenCV cannot decode.
    """
    if not body:
        raise DataError("the request body is empty: send the encoded image (PNG or JPEG)")
    kind = image_format(body)
    data = np.frombuffer(body, dtype=np.uint8)
    check_pixels(data, max_pixels)
    if is_16_bit_grey_png(data):
        raise DataError(
            "the request body is a 16-bit single-channel PNG (a depth map?), not a colour image"
        )
    # Trailing zero padding is common; anything else after the data would not be.
    if kind == "jpeg" and not body.rstrip(b"\x00").endswith(JPEG_END):
        raise DataError("the request body is a truncated JPEG (its end-of-image marker is missing)")
    try:
        image = cv2.imdecode(data, cv2.IMREAD_COLOR)
    except cv2.error as error:
        message = str(error).strip().splitlines()[-1]
        raise DataError(f"cannot decode the request body's {kind.upper()}: {message}") from error
    if image is None:
        raise DataError(f"cannot decode the request body's {kind.upper()} (truncated or corrupt)")
    return np.ascontiguousarray(image[:, :, ::-1])
