"""The request body: an encoded PNG or JPEG, checked before and after decoding.

The checks are relocfw.core.imaging's, which `task=localize` runs on files (the
header read as the decoder reads it and its announced size and shape, a 16-bit grey
PNG refused as a depth map, OpenCV's colour decoding: 16-bit colour scaled to 8 bits,
alpha dropped), plus what a service needs on top: only PNG and JPEG (the two formats
whose headers are read before decoding, so no other format can announce a
decompression bomb), a tighter pixel limit (serve.max_pixels) and a JPEG refused when
no end marker follows its image data (OpenCV decodes such a file with its missing rows
grey and only a warning on stderr; bytes after the end marker, such as a Motion
Photo's video, are fine).
"""

from __future__ import annotations

import cv2
import numpy as np

from relocfw.core.errors import DataError
from relocfw.core.image_headers import JPEG_START, PNG_SIGNATURE, jpeg_has_end
from relocfw.core.imaging import (
    MAX_ASPECT,
    check_aspect,
    check_header,
    cv2_message,
    is_16_bit_grey_png,
    out_of_memory,
)

# How the imaging checks name what they read: the body, never a path.
BODY = "the request body"


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


def check_pixels(data: np.ndarray, max_pixels: int, max_aspect: float = MAX_ASPECT) -> None:
    """Refuse, before decoding, a damaged header or one announcing more than
    imaging.MAX_IMAGE_PIXELS or an image thinner than `max_aspect` (imaging's own
    messages), or more than `max_pixels` (serve.max_pixels)."""
    header = check_header(data, BODY, max_aspect, key="query.max_aspect")
    if header is None:  # image_format let only PNG and JPEG through
        raise DataError("the request body is not a PNG or JPEG image")
    if header.width * header.height > max_pixels:
        raise DataError(
            f"the request body's header announces {header.width} x {header.height} pixels, "
            f"more than the {max_pixels} this service decodes (serve.max_pixels); "
            "scale the image down"
        )


def decode_image(body: bytes, max_pixels: int, max_aspect: float = MAX_ASPECT) -> np.ndarray:
    """H x W x 3 uint8 RGB pixels of an encoded PNG or JPEG.

    Args:
        body: the encoded image.
        max_pixels: the most pixels its header may announce (serve.max_pixels).
        max_aspect: the most its long side may be times its short side
            (query.max_aspect of the model the service answers with).

    Raises:
        DataError: one line saying what is wrong: an empty body, not a PNG or JPEG, a
            damaged header, one announcing too many pixels or too thin an image, a
            16-bit grey PNG (a depth map), a JPEG without its end marker (truncated),
            bytes OpenCV cannot decode or too large to decode in the memory there is.
    """
    if not body:
        raise DataError("the request body is empty: send the encoded image (PNG or JPEG)")
    kind = image_format(body)
    data = np.frombuffer(body, dtype=np.uint8)
    check_pixels(data, max_pixels, max_aspect)
    if is_16_bit_grey_png(data):
        raise DataError(
            "the request body is a 16-bit single-channel PNG (a depth map?), not a colour image"
        )
    # After the end marker phones put more (a Motion Photo's video): only its absence counts.
    if kind == "jpeg" and not jpeg_has_end(body, BODY):
        raise DataError(
            "the request body is a truncated JPEG (no end-of-image marker after its image data)"
        )
    try:
        image = cv2.imdecode(data, cv2.IMREAD_COLOR)
    except cv2.error as error:
        message = cv2_message(error)
        raise DataError(f"cannot decode the request body's {kind.upper()}: {message}") from error
    except MemoryError as error:
        raise DataError(out_of_memory(BODY, "decoding it")) from error
    if image is None:
        raise DataError(f"cannot decode the request body's {kind.upper()} (truncated or corrupt)")
    check_aspect(image.shape[1], image.shape[0], f"{BODY} is", max_aspect)
    return np.ascontiguousarray(image[:, :, ::-1])
