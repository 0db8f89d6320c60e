"""The size a PNG or JPEG header announces, read the way the decoders read it.

One reader for every place relocfw decodes bytes from elsewhere (image files, bag
messages, the service's request bodies), so a limit checked on the header is checked
on the size the decoder will allocate. A reader that disagrees with the decoder is a
way past the limit: a crafted file shows it one size and the decoder another.

JPEG (ITU T.81, B.1.1): after SOI the header is a run of markers, each `FF` `xx`
after any number of `FF` fill bytes. SOI, EOI, RST0-RST7 and TEM stand alone; every
other marker starts a segment whose two-byte length counts itself. The frame size is
in the first start-of-frame segment (SOF0-SOF15 less DHT, JPG and DAC). Bytes between
segments that are not a marker are skipped, as libjpeg skips them (with a warning),
so the frame header found is the one libjpeg decodes. Where the reader and libjpeg
differ, the reader refuses what libjpeg would read: a segment length of 0 or 1
(libjpeg skips nothing and reads on), a frame height of 0 (a height given later in a
DNL segment, which libjpeg does not decode either), and more than JPEG_MOST_MARKERS
markers before the first scan.

A crafted header costs the walk no more than one pass over the data in C: bytes
between segments and a run of fill bytes are each skipped by one C-level search, and
the Python steps (one per marker or stuffed zero, FF 00) are capped by
JPEG_MOST_MARKERS.

PNG: libpng refuses a file whose first chunk is not a 13-byte IHDR, and a width or
height of 0 or above 2^31 - 1 (png_get_uint_31).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from relocfw.core.errors import DataError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_START = b"\xff\xd8"
# Markers without a length: SOI, RST0-RST7, TEM (EOI ends the header: handled apart).
JPEG_STANDALONE = frozenset({0xD8, *range(0xD0, 0xD8), 0x01})
JPEG_END_OF_IMAGE = 0xD9
JPEG_END = b"\xff\xd9"
JPEG_START_OF_SCAN = 0xDA
# Start-of-frame markers: C0-CF less C4 (DHT), C8 (JPG, reserved) and CC (DAC).
JPEG_FRAME_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# A frame header's fixed part: length (2), precision (1), height (2), width (2), Nf (1).
JPEG_FRAME_FIXED = 8
# The most markers (and FF 00 pairs, which libjpeg skips) read from SOI to the first
# scan. A camera writes fewer than 100 markers (APPn blocks, tables), and an ICC
# profile is split into at most 255 APP2 chunks. More is a crafted header (millions of
# 4-byte comments, TEM markers or FF 00 pairs in a 20 MB body, each a Python step):
# refused as damaged.
JPEG_MOST_MARKERS = 1024
JPEG_FILL = re.compile(rb"\xff+")  # a marker's FF and the fill bytes before it
PNG_IHDR_LENGTH = 13
PNG_LARGEST = 2**31 - 1  # png_get_uint_31's bound


@dataclass(frozen=True)
class ImageHeader:
    """What an image header announces."""

    format: str  # "png" or "jpeg"
    width: int
    height: int


def read_header(data: bytes | np.ndarray, name: str) -> ImageHeader | None:
    """The format and size a PNG or JPEG header announces; None for other formats
    (and for empty data), whose headers are not read.

    Args:
        data: the encoded image, as bytes or a uint8 array.
        name: how a refusal names the data (a file, a bag topic, the request body).

    Raises:
        DataError: naming `name`, for a PNG or JPEG header that is damaged or cut
            short: the decoder would refuse it, or read it differently.
    """
    raw = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
    if raw.startswith(PNG_SIGNATURE):
        return png_header(raw, name)
    if raw.startswith(JPEG_START):
        return jpeg_header(raw, name)
    return None


def png_header(data: bytes, name: str) -> ImageHeader:
    """The size in a PNG's IHDR, which must be its first chunk."""

    def damaged(problem: str) -> DataError:
        return DataError(f"{name}: damaged PNG header ({problem})")

    start = len(PNG_SIGNATURE)
    if len(data) < start + 8 + PNG_IHDR_LENGTH:
        raise damaged("it ends before its IHDR chunk")
    length = int.from_bytes(data[start : start + 4], "big")
    if data[start + 4 : start + 8] != b"IHDR" or length != PNG_IHDR_LENGTH:
        raise damaged("its first chunk is not a 13-byte IHDR")
    fields = start + 8
    width = int.from_bytes(data[fields : fields + 4], "big")
    height = int.from_bytes(data[fields + 4 : fields + 8], "big")
    for axis, value in (("width", width), ("height", height)):
        if not 0 < value <= PNG_LARGEST:
            raise damaged(f"its {axis} is {value}, outside 1 to {PNG_LARGEST}")
    return ImageHeader("png", width, height)


def jpeg_damaged(name: str, problem: str) -> DataError:
    return DataError(f"{name}: damaged JPEG header ({problem})")


def jpeg_header(data: bytes, name: str) -> ImageHeader:
    """The size in a JPEG's first frame header, its markers walked from SOI."""
    for marker, offset, length in jpeg_markers(data, name):
        if marker == JPEG_END_OF_IMAGE:
            raise jpeg_damaged(name, "the image ends before its frame header")
        if marker == JPEG_START_OF_SCAN:
            raise jpeg_damaged(name, "a scan starts before the frame header")
        if marker in JPEG_FRAME_MARKERS:
            if length < JPEG_FRAME_FIXED:
                raise jpeg_damaged(name, f"a frame header of {length} bytes, too short for a size")
            height = int.from_bytes(data[offset + 3 : offset + 5], "big")
            width = int.from_bytes(data[offset + 5 : offset + 7], "big")
            if width == 0 or height == 0:  # a height given later (DNL): not decoded
                raise jpeg_damaged(name, f"its frame header announces {width} x {height} pixels")
            return ImageHeader("jpeg", width, height)
    raise jpeg_damaged(name, "the data ends before its frame header")


def jpeg_has_end(data: bytes, name: str) -> bool:
    """Whether a JPEG's end-of-image marker (EOI, FF D9) follows its first scan.

    The markers are walked to the first start of scan, then its entropy-coded data is
    searched for FF D9 in one step: an FF there is always followed by 00 (a stuffed
    zero) or a restart marker, so the first FF D9 after it ends the image (or a later
    scan's table, rarely: then the file is decoded as OpenCV would). Bytes after EOI (a
    Motion Photo's video, a Samsung trailer) do not matter; a file cut inside its scans
    has none. A file without a scan has nothing to cut: True, and the decoder refuses it.

    Raises:
        DataError: naming `name`, for a damaged header (see jpeg_markers).
    """
    for marker, offset, length in jpeg_markers(data, name):
        if marker == JPEG_START_OF_SCAN:
            return data.find(JPEG_END, offset + length) >= 0
        if marker == JPEG_END_OF_IMAGE:
            return True
    return False


def jpeg_markers(data: bytes, name: str) -> Iterator[tuple[int, int, int]]:
    """(marker, offset just after it, its segment's length or 0 for a marker that
    stands alone) of each marker after SOI, in order, as libjpeg's next_marker finds
    them: fill bytes before a marker swallowed, other bytes (FF 00, a stuffed zero,
    too) skipped. Ends at the end of the data; the caller stops at the marker it wants.

    Raises:
        DataError: naming `name`, at a segment whose length is below 2 or runs past
            the end, or past JPEG_MOST_MARKERS markers and FF 00 pairs.
    """
    offset = len(JPEG_START)
    for _ in range(JPEG_MOST_MARKERS):
        start = data.find(b"\xff", offset)  # bytes before it skipped, as libjpeg does
        if start < 0:
            return
        offset = JPEG_FILL.match(data, start).end()  # one C step past any fill bytes
        if offset >= len(data):
            return
        marker, offset = data[offset], offset + 1
        if marker == 0x00:  # FF 00, a stuffed zero: not a marker
            continue
        if marker in JPEG_STANDALONE or marker == JPEG_END_OF_IMAGE:
            yield marker, offset, 0
            continue
        if offset + 2 > len(data):
            raise jpeg_damaged(name, "the data ends inside a segment's length")
        length = int.from_bytes(data[offset : offset + 2], "big")
        if length < 2:
            raise jpeg_damaged(
                name, f"a segment length of {length}, below the 2 bytes of the length"
            )
        if offset + length > len(data):
            raise jpeg_damaged(
                name, f"a segment of {length} bytes at byte {offset} runs past the end"
            )
        yield marker, offset, length
        offset += length
    raise jpeg_damaged(
        name,
        f"more than {JPEG_MOST_MARKERS} markers or FF 00 pairs before its image data, "
        "where a camera writes fewer than 100 markers",
    )
