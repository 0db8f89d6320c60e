"""Reading images and cutting square network inputs out of them."""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from relocfw.core.errors import DataError
from relocfw.core.image_headers import PNG_SIGNATURE, ImageHeader, read_header
from relocfw.core.interfaces import crop_at, crop_side_and_span
from relocfw.core.values import Crop

# The largest image read_rgb decodes: OpenCV's own limit, 2^30 pixels (3 GiB as RGB;
# a 200 MP photo is well inside). Checked on the header before decoding, so an image
# announcing more (70000 x 70000) is one DataError naming the file, not OpenCV's
# cv2.error that names none.
MAX_IMAGE_PIXELS = 2**30
# The thinnest image a query may be (long side / short side: query.max_aspect). The
# strip scales the short side up to the network input, so its memory and the crops a
# sweep tries grow with this ratio: a 1 x 20000 strip is 6 GB. 10 passes every camera
# frame (16:9 is 1.8), 2:1 equirectangular panoramas, 6:1 cube-map strips and phone
# panoramas (about 4:1 to 9:1), and bounds a strip at 10 network inputs side by side.
MAX_ASPECT = 10.0


def read_rgb(path: Path, max_aspect: float = math.inf, key: str | None = None) -> np.ndarray:
    """RGB uint8 image (H x W x 3); grey images are expanded to three channels.

    Args:
        path: the image file.
        max_aspect: the most its long side may be times its short side (checked on a
            PNG or JPEG header before decoding, and on the pixels of every image). No
            limit by default: a map image is not a query; a query's shape is checked
            where it is queried (relocfw.core.query_windows) or by a caller reading
            queries (task=localize's files, with query.max_aspect).
        key: the option that set `max_aspect`, named in a refusal (None: none did).

    Raises:
        DataError: naming the file, when it is missing or cannot be decoded, when its
            header is damaged or announces more than MAX_IMAGE_PIXELS pixels, when it
            is thinner than `max_aspect` allows, or when it is a 16-bit single-channel
            PNG or TIFF (a depth map, not a colour image).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"image not found: {path}")
    data = np.fromfile(path, dtype=np.uint8)
    check_header(data, str(path), max_aspect, key)
    if is_16_bit_grey_png(data):
        raise DataError(f"{path} is a 16-bit single-channel PNG (a depth map?), not a colour image")
    try:
        if is_single_channel_deep_tiff(data):
            raise DataError(
                f"{path} is a 16-bit or float single-channel TIFF (a depth map?), "
                "not a colour image"
            )
        image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    except cv2.error as error:  # e.g. a size past OpenCV's limit in a format not parsed here
        raise DataError(f"cannot decode image {path}: {cv2_message(error)}") from error
    except MemoryError as error:
        raise DataError(out_of_memory(str(path), "decoding it")) from error
    if image is None:
        raise DataError(f"cannot decode image (corrupt or not an image): {path}")
    check_aspect(image.shape[1], image.shape[0], f"{path} is", max_aspect, key)
    return np.ascontiguousarray(image[:, :, ::-1])


def cv2_message(error: cv2.error) -> str:
    """The last line of OpenCV's message: the one that says what went wrong."""
    return str(error).strip().splitlines()[-1]


def out_of_memory(name: str, doing: str) -> str:
    """The message for an allocation that failed, naming the limits that bound it."""
    return (
        f"{name}: out of memory {doing}; an image's size is bounded by its pixels "
        f"({MAX_IMAGE_PIXELS}, serve.max_pixels for the service) and its shape "
        "(query.max_aspect): scale the image down or lower the limits"
    )


def check_header(
    data: np.ndarray | bytes, name: str, max_aspect: float = math.inf, key: str | None = None
) -> ImageHeader | None:
    """A PNG or JPEG header, read and checked before decoding; None for other formats.

    Args:
        data: the encoded image.
        name: how a refusal names it (a file, a bag message, the request body).
        max_aspect: the most its long side may be times its short side (no limit by
            default); `key`: the option that set it (see check_aspect).

    Raises:
        DataError: naming `name`, for a damaged header, one announcing more than
            MAX_IMAGE_PIXELS pixels, or an image thinner than `max_aspect` allows.
    """
    header = read_header(data, name)
    if header is None:
        return None
    width, height = header.width, header.height
    if width * height > MAX_IMAGE_PIXELS:
        raise DataError(
            f"{name}: its header announces {width} x {height} pixels, more than the "
            f"{MAX_IMAGE_PIXELS} relocfw decodes (a corrupt header, or scale the image down)"
        )
    check_aspect(width, height, f"{name}: its header announces", max_aspect, key)
    return header


def check_aspect(
    width: int,
    height: int,
    what: str,
    max_aspect: float = MAX_ASPECT,
    key: str | None = "query.max_aspect",
) -> None:
    """Refuse an image whose long side is more than `max_aspect` times its short side
    (query.max_aspect for a query): its strip and its crop searches grow with that ratio.

    Args:
        what: the start of the message, naming the image: "x.png is", "x.png: its
            header announces".
        key: the option that set `max_aspect`, named in the refusal; None where no
            option did, so the message never points at a key that would not help.
    """
    long, short = max(width, height), min(width, height)
    if long > max_aspect * short:
        limit = f"{key}={max_aspect:g}" if key else f"{max_aspect:g}"
        remedy = f"crop the image, or raise {key}" if key else "crop the image"
        raise DataError(
            f"{what} {width} x {height} pixels, its long side {long / max(short, 1):.4g} "
            f"times its short side, more than {limit} allows ({remedy})"
        )


def is_16_bit_grey_png(data: np.ndarray) -> bool:
    """Whether PNG bytes hold a 16-bit grey image: how 7-Scenes, TUM and the synthetic
    scene store depth. Decoded as colour it would silently become a nonsense image,
    so the header is read first (IHDR: bit depth at byte 24, colour type at 25)."""
    if data.size < 26 or data[:8].tobytes() != PNG_SIGNATURE:
        return False
    return int(data[24]) == 16 and int(data[25]) in (0, 4)  # grey, grey + alpha


TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*")


def is_single_channel_deep_tiff(data: np.ndarray) -> bool:
    """Whether TIFF bytes hold a single-channel 16-bit or float image: how depth maps
    are often stored as TIFF. Decoded as colour it would become a nonsense image; the
    TIFF is decoded unchanged to tell (TIFF headers are not parsed here)."""
    if data.size < 4 or data[:4].tobytes() not in TIFF_SIGNATURES:
        return False
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        return False
    return image.ndim == 2 and image.dtype in (np.uint16, np.float32, np.float64)


def conversion_hint(dtype: np.dtype) -> str:
    """How to make uint8 pixels of what a user most often has instead ("" if unknown)."""
    if dtype.kind == "f":
        return " (a float image in [0, 1]: (image * 255).round().astype(np.uint8))"
    if dtype == np.uint16:
        return " (a 16-bit image: (image >> 8).astype(np.uint8))"
    return ""


def check_rgb_image(image: object, name: str = "image") -> np.ndarray:
    """`image` itself if it is an H x W x 3 uint8 RGB numpy array; DataError if not.

    The pipeline takes uint8 pixels only: a float image in [0, 1] would be divided by
    255 a second time and a uint16 image read as if it were 8-bit, both silently, and a
    greyscale or RGBA array would fail deep inside torch. Checking costs no copy.

    Args:
        image: what the caller passed.
        name: how the message names it, e.g. "image 3" for the fourth of a list.

    Raises:
        DataError: naming the dtype or shape found and what to do about it.
    """
    if not isinstance(image, np.ndarray):
        raise DataError(
            f"{name} is a {type(image).__name__}; relocfw takes numpy arrays, "
            "H x W x 3 uint8 RGB (relocfw.core.imaging.read_rgb reads a file that way)"
        )
    if image.dtype != np.uint8:
        raise DataError(
            f"{name} has dtype {image.dtype}; relocfw takes H x W x 3 uint8 RGB images"
            + conversion_hint(image.dtype)
        )
    if image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
        raise DataError(
            f"{name} has shape {image.shape}; relocfw takes H x W x 3 uint8 RGB images "
            "(greyscale: np.repeat(image[..., None], 3, axis=2); RGBA: image[..., :3])"
        )
    return image


def check_rgb_images(images: Sequence[object]) -> None:
    """check_rgb_image on every image of a list, naming the first bad one by index."""
    for number, image in enumerate(images):
        check_rgb_image(image, f"image {number}")


class Strip:
    """An image scaled so its short side equals the network input, ready to crop.

    Every square crop of the original image is a window of this strip: scaling once
    and cutting windows is the same as cutting then scaling each crop (up to
    sub-pixel rounding of the offset), and far cheaper when a search tries many.

    With `crop_scale` > 1 (a model trained with PoseNet's crops, see
    `TrainSettings.crop_scale`) the short side is scaled to crop_scale x the input and
    the window of a crop is the input-sized square at the crop's centre: the network
    sees the central 1/crop_scale of every crop, the field of view it was trained on.
    """

    def __init__(self, image: np.ndarray, input_size: int, crop_scale: float = 1.0) -> None:
        self.height, self.width = image.shape[:2]
        short, _ = crop_side_and_span(self.width, self.height)
        self.input_size = input_size
        self.side = max(input_size, round(input_size * crop_scale))  # a crop's side here
        self.scale = self.side / short
        # Where the input-sized window sits inside a crop's scaled square.
        self.margin = (self.side - input_size) / 2
        size = (
            max(self.side, round(self.width * self.scale)),
            max(self.side, round(self.height * self.scale)),
        )
        interpolation = cv2.INTER_AREA if self.scale < 1 else cv2.INTER_LINEAR
        try:  # the strip of a thin image is large: one that cannot be made is refused
            scaled = cv2.resize(image, size, interpolation=interpolation)
            self.pixels = torch.from_numpy(np.ascontiguousarray(scaled.transpose(2, 0, 1)))
        except (cv2.error, MemoryError) as error:
            what = f"a {self.width} x {self.height} image"
            doing = f"scaling it to its {size[0]} x {size[1]} strip"
            if isinstance(error, cv2.error):
                doing += f" ({cv2_message(error)})"
            raise DataError(out_of_memory(what, doing)) from error

    def window(self, crop: Crop) -> tuple[int, int]:
        """Top-left corner in the strip of the window that shows `crop`."""
        x = min(round(crop.x * self.scale + self.margin), self.pixels.shape[2] - self.input_size)
        y = min(round(crop.y * self.scale + self.margin), self.pixels.shape[1] - self.input_size)
        return y, x

    def cut(self, corner: tuple[int, int]) -> torch.Tensor:
        """uint8 [3, s, s] network input at a strip corner."""
        y, x = corner
        s = self.input_size
        return self.pixels[:, y : y + s, x : x + s]

    def centre_crop(self) -> Crop:
        _, span = crop_side_and_span(self.width, self.height)
        return crop_at(span // 2, self.width, self.height)


def image_fingerprint(image: np.ndarray) -> int:
    """A 64-bit integer that names an image by its pixels (shape included).

    Crop searches seed their per-query random stream from it: the same image always
    gets the same stream, different images independent ones.
    """
    pixels = np.ascontiguousarray(image)
    digest = hashlib.blake2b(str(pixels.shape).encode(), digest_size=8)
    digest.update(pixels.tobytes())
    return int.from_bytes(digest.digest(), "little")


def to_network_input(batch: torch.Tensor) -> torch.Tensor:
    """uint8 [B, 3, s, s] -> float in [0, 1]; the backbone normalises further."""
    return batch.float().div_(255.0)
