"""Pixels of ROS image messages (sensor_msgs/Image, CompressedImage) as numpy arrays.

Plain functions of a decoded message's fields (no rosbags import), so a message from
any bag reader decodes the same way. Every size is checked against the buffer before
it is used, and a CompressedImage's header is read by the reader files and the
service use (relocfw.core.imaging.check_header) before it is decoded: a bag is data
from someone else, and one bad message is one DataError naming its topic and stamp,
which on_error=skip leaves out.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import check_header, cv2_message, out_of_memory

COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
# sensor_msgs/Image encodings read as colour: channels of 8 bits each.
COLOUR_CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgba8": 4, "bgra8": 4}
# Depth encodings, with the metres one stored unit is (16-bit: millimetres).
DEPTH_ENCODINGS = {"16UC1": 0.001, "mono16": 0.001, "32FC1": 1.0}


def raw_pixels(message: Any, channels: int, dtype: np.dtype, topic: str) -> np.ndarray:
    """A sensor_msgs/Image's rows as an [H, W, channels] array of `dtype`, honouring
    `step` (row padding) and `is_bigendian`, after checking the buffer is big enough."""
    height, width, step = int(message.height), int(message.width), int(message.step)
    row = width * channels * dtype.itemsize
    data = np.asarray(message.data, dtype=np.uint8)
    if height < 1 or width < 1 or step < row or data.size < step * height:
        raise DataError(
            f"{topic}: {message.encoding} image of {width}x{height}, step {step}, holds "
            f"{data.size} bytes: too few"
        )
    rows = data[: step * height].reshape(height, step)[:, :row]
    order = ">" if message.is_bigendian else "<"
    pixels = np.ascontiguousarray(rows).view(dtype.newbyteorder(order))
    return pixels.reshape(height, width, channels).astype(dtype)


def colour_image(message: Any, msgtype: str, topic: str) -> np.ndarray:
    """The H x W x 3 uint8 RGB pixels of an Image or CompressedImage message.

    Its shape is not checked here: a query's (query.max_aspect) is checked where the
    configured limit is known, as for any frame.

    Raises:
        ConfigError: naming the topic when it holds depth (16UC1, 32FC1): a wrong topic.
        DataError: naming the topic and the message's stamp when it cannot be decoded
            (a damaged header, one announcing more than imaging.MAX_IMAGE_PIXELS,
            OpenCV's refusal or an allocation that fails).
    """
    if msgtype == COMPRESSED_IMAGE:
        return compressed_colour(message, f"{topic} (stamp {stamp_text(message)})")
    encoding = str(message.encoding)
    if encoding in DEPTH_ENCODINGS:
        raise ConfigError(
            f"{topic} holds {encoding} depth images, not colour: give a colour topic "
            "(rgb8, bgr8, mono8, rgba8, bgra8 or compressed)"
        )
    channels = COLOUR_CHANNELS.get(encoding)
    if channels is None:
        raise DataError(
            f"{topic}: image encoding {encoding!r} is not read (rgb8, bgr8, mono8, rgba8, bgra8)"
        )
    pixels = raw_pixels(message, channels, np.dtype(np.uint8), topic)
    if encoding == "mono8":
        pixels = np.repeat(pixels, 3, axis=2)
    elif encoding.startswith("bgr"):
        pixels = pixels[:, :, 2::-1]
    return np.ascontiguousarray(pixels[:, :, :3])


def compressed_colour(message: Any, name: str) -> np.ndarray:
    """A CompressedImage's RGB pixels; refusals name the message as `name`.

    Only PNG and JPEG are decoded (the formats image_transport writes), as the service
    decodes only those: their headers are read before decoding, while another format
    (TIFF, WebP, GIF) could announce up to OpenCV's own 2^30 pixels.
    """
    data = np.asarray(message.data, dtype=np.uint8)
    what = f"compressed image ({message.format})"
    if data.size == 0:
        raise DataError(f"{name}: {what} is empty")
    # No aspect limit here: see colour_image.
    if check_header(data, f"{name}: {what}") is None:
        raise DataError(
            f"{name}: {what} is not a PNG or JPEG image (its first bytes are neither); "
            "only those two are decoded, their size read before decoding"
        )
    try:
        decoded = cv2.imdecode(data, cv2.IMREAD_COLOR)
    except cv2.error as error:  # e.g. an allocation OpenCV refuses
        raise DataError(f"{name}: {what} does not decode: {cv2_message(error)}") from error
    except MemoryError as error:
        raise DataError(out_of_memory(f"{name}: {what}", "decoding it")) from error
    if decoded is None:
        raise DataError(f"{name}: {what} does not decode")
    return np.ascontiguousarray(decoded[:, :, ::-1])


def stamp_text(message: Any) -> str:
    """The message header's stamp as seconds.nanoseconds ("unknown" without one)."""
    stamp = getattr(getattr(message, "header", None), "stamp", None)
    try:
        return f"{int(stamp.sec)}.{int(stamp.nanosec):09d}"
    except (AttributeError, TypeError, ValueError):
        return "unknown"


def depth_image(message: Any, topic: str) -> np.ndarray:
    """[H, W] float32 metres of a 16UC1 (millimetres) or 32FC1 (metres) depth image;
    NaN where there is no reading (0, or not finite).

    Raises:
        DataError: naming the topic for another encoding or a short buffer.
    """
    encoding = str(message.encoding)
    metres = DEPTH_ENCODINGS.get(encoding)
    if metres is None:
        raise DataError(f"{topic}: depth encoding {encoding!r} is not read (16UC1 mm, 32FC1 m)")
    dtype = np.dtype(np.float32 if encoding == "32FC1" else np.uint16)
    values = raw_pixels(message, 1, dtype, topic)[:, :, 0].astype(np.float32) * np.float32(metres)
    values[~np.isfinite(values) | (values <= 0)] = np.nan
    return values
