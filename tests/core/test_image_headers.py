"""The image-header reader that files, bags and the service share: JPEG markers walked
as ITU T.81 B.1.1 defines them (and as libjpeg reads them), a PNG's IHDR as libpng
reads it. Each crafted file is checked against what OpenCV's decoder makes of it."""

import struct
import time
import zlib

import cv2
import numpy as np
import pytest

from relocfw.core.errors import DataError
from relocfw.core.image_headers import JPEG_START, ImageHeader, read_header
from relocfw.core.imaging import read_rgb
from relocfw.serve.images import decode_image

COM = 0xFE


def jpeg(height: int = 48, width: int = 64, **flags: int) -> bytes:
    pixels = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    params = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if flags.get("progressive") else []
    return cv2.imencode(".jpg", pixels, params)[1].tobytes()


def segment(marker: int, payload: bytes) -> bytes:
    return bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload


def fake_frame_header(width: int, height: int) -> bytes:
    """An SOF0 marker segment (precision, height, width, three components)."""
    components = b"\x01\x11\x00\x02\x11\x01\x03\x11\x01"
    return segment(0xC0, struct.pack(">BHHB", 8, height, width, 3) + components)


def tem_trap(real: bytes) -> bytes:
    """`real` with a TEM marker (FF01, no length) after SOI, then two comments; a
    reader that takes FF01 for a segment reads the next two bytes (FF FE) as a
    length, skips 65534 bytes and lands on an 8 x 8 frame header inside the second
    comment, while libjpeg skips TEM alone and reads the real frame header after."""
    first = segment(COM, b"c" * 40000)
    landing = 2 + 2 + 0xFFFE  # where a reader that skips FF01's "length" lands
    before_fake = landing - (2 + 2 + len(first) + 4)  # bytes of comment 2 before it
    second = segment(COM, b"d" * before_fake + fake_frame_header(8, 8) + b"e" * 16)
    trapped = real[:2] + b"\xff\x01" + first + second + real[2:]
    assert trapped[landing : landing + 2] == b"\xff\xc0"
    return trapped


def with_frame_size(data: bytes, width: int, height: int) -> bytes:
    """`data` with its last SOF0 segment announcing width x height (the real one)."""
    at = data.rindex(b"\xff\xc0")
    return data[: at + 5] + struct.pack(">HH", height, width) + data[at + 9 :]


def decoded_size(data: bytes) -> tuple[int, int]:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return image.shape[1], image.shape[0]


def test_tem_is_a_marker_without_a_length_and_the_real_frame_header_is_read():
    trapped = tem_trap(jpeg(48, 64))
    # libjpeg skips TEM and decodes the real 64 x 48 frame: the reader agrees.
    assert decoded_size(trapped) == (64, 48)
    assert read_header(trapped, "x.jpg") == ImageHeader("jpeg", 64, 48)


def test_the_tem_trap_does_not_pass_the_service_pixel_limit(tmp_path):
    trapped = tem_trap(jpeg(48, 64))
    with pytest.raises(DataError, match=r"64 x 48 pixels, more than the 1000"):
        decode_image(trapped, max_pixels=1000)
    # A file announcing more than OpenCV's own 2^30 pixels behind the trap: refused
    # on its header, naming the file and the real size.
    bomb = tmp_path / "bomb.jpg"
    bomb.write_bytes(with_frame_size(trapped, 40000, 40000))
    with pytest.raises(DataError, match=r"bomb\.jpg: its header announces 40000 x 40000"):
        read_rgb(bomb)


def test_restart_markers_fill_bytes_and_soi_stand_alone():
    real = jpeg(30, 20)
    # RST0-RST7 and SOI carry no length; any number of FF fill bytes may precede a marker.
    standalone = b"".join(bytes([0xFF, m]) for m in range(0xD0, 0xD8))
    crafted = real[:2] + standalone + b"\xff" * 5 + segment(COM, b"hi") + real[2:]
    assert decoded_size(crafted) == (20, 30)
    assert read_header(crafted, "x.jpg") == ImageHeader("jpeg", 20, 30)
    # Bytes between segments, stuffed zeros among them, are skipped (libjpeg warns);
    # here after APP0 (OpenCV takes a file for JPEG by FF D8 FF).
    padded = real[:20] + b"\x00\x17\xff\x00\xff\xff\x00" + real[20:]
    assert decoded_size(padded) == (20, 30)
    assert read_header(padded, "x.jpg") == ImageHeader("jpeg", 20, 30)


def test_progressive_and_other_frame_kinds_are_frame_headers():
    progressive = jpeg(40, 24, progressive=1)
    assert b"\xff\xc2" in progressive  # SOF2
    assert read_header(progressive, "p.jpg") == ImageHeader("jpeg", 24, 40)
    # DHT (C4), JPG (C8) and DAC (CC) are not frame headers, whatever they hold (libjpeg
    # refuses a file with JPG before its frame: the reader's answer is never the size).
    for marker in (0xC4, 0xC8, 0xCC):
        fake = segment(marker, struct.pack(">BHHB", 8, 9, 9, 3))
        crafted = progressive[:2] + fake + progressive[2:]
        assert read_header(crafted, "p.jpg") == ImageHeader("jpeg", 24, 40)


def test_a_frame_height_given_later_dnl_is_refused_as_libjpeg_refuses_it():
    real = jpeg(48, 64)
    at = real.index(b"\xff\xc0")
    no_height = real[: at + 5] + struct.pack(">H", 0) + real[at + 7 :]
    assert cv2.imdecode(np.frombuffer(no_height, np.uint8), cv2.IMREAD_COLOR) is None
    with pytest.raises(DataError, match=r"damaged JPEG header \(its frame header announces 64 x 0"):
        read_header(no_height, "x.jpg")


def exif_with_thumbnail(thumbnail: bytes) -> bytes:
    """An APP1 Exif segment as a camera writes it: IFD0 (orientation 1), then IFD1
    pointing at a JPEG thumbnail held inside the segment (its own SOI, SOF, EOI)."""
    ifd0 = struct.pack("<H", 1) + struct.pack("<HHII", 0x0112, 3, 1, 1) + struct.pack("<I", 26)
    thumbnail_at = 26 + 2 + 2 * 12 + 4
    ifd1 = struct.pack("<H", 2)
    ifd1 += struct.pack("<HHII", 0x0201, 4, 1, thumbnail_at)  # JPEGInterchangeFormat
    ifd1 += struct.pack("<HHII", 0x0202, 4, 1, len(thumbnail))  # ...Length
    ifd1 += struct.pack("<I", 0)
    tiff = b"II*\x00" + struct.pack("<I", 8) + ifd0 + ifd1 + thumbnail
    return segment(0xE1, b"Exif\x00\x00" + tiff)


def test_a_camera_header_exif_thumbnail_icc_adobe_gives_the_decoded_size():
    real = jpeg(48, 64)
    assert real[2:4] == b"\xff\xe0"  # APP0 (JFIF), 20 bytes with SOI: a camera writes Exif
    thumbnail = jpeg(12, 16)
    icc = segment(0xE2, b"ICC_PROFILE\x00\x01\x01" + bytes(range(256)) * 2)
    adobe = segment(0xEE, b"Adobe" + struct.pack(">HHHB", 100, 0, 0, 1))  # YCbCr
    camera = real[:2] + exif_with_thumbnail(thumbnail) + icc + adobe + real[20:]
    assert camera.index(b"\xff\xc0") < camera.rindex(b"\xff\xc0")  # the thumbnail's first
    assert decoded_size(camera) == (64, 48)
    assert read_header(camera, "camera.jpg") == ImageHeader("jpeg", 64, 48)


@pytest.mark.parametrize(
    ("inserted", "problem"),
    [
        (b"\xff\xfe\x00\x01", "segment length of 1"),
        (b"\xff\xfe\x00\x00", "segment length of 0"),
        (b"\xff\xfe\xff\xf0abc", "runs past the end"),
        (segment(0xDA, b"\x01\x01\x00\x00\x3f\x00"), "scan starts before the frame header"),
        (b"\xff\xd9", "ends before its frame header"),
    ],
)
def test_a_damaged_jpeg_header_is_refused_in_one_line(inserted, problem):
    crafted = jpeg()[:2] + inserted
    if not inserted.startswith(b"\xff\xfe\xff"):
        crafted += jpeg()[2:]
    with pytest.raises(DataError, match=rf"^x\.jpg: damaged JPEG header \(.*{problem}"):
        read_header(crafted, "x.jpg")


def test_a_truncated_jpeg_header_is_refused():
    assert jpeg()[2:4] == b"\xff\xe0" and jpeg()[4:6] == b"\x00\x10"  # APP0, 16 bytes
    with pytest.raises(DataError, match=r"damaged JPEG header \(the data ends before its frame"):
        read_header(jpeg()[:20], "x.jpg")  # cut after APP0
    with pytest.raises(DataError, match=r"damaged JPEG header \(a segment of 16 bytes .* past"):
        read_header(jpeg()[:19], "x.jpg")  # cut inside APP0


def png(height: int = 4, width: int = 6) -> bytes:
    return cv2.imencode(".png", np.zeros((height, width, 3), np.uint8))[1].tobytes()


def chunk(kind: bytes, payload: bytes) -> bytes:
    crc = struct.pack(">I", zlib.crc32(kind + payload))
    return struct.pack(">I", len(payload)) + kind + payload + crc


def test_png_size_is_read_from_the_ihdr_chunk():
    assert read_header(png(4, 6), "x.png") == ImageHeader("png", 6, 4)
    # A chunk before IHDR: libpng refuses the file ("missing IHDR"), so does the reader.
    data = png(4, 6)
    moved = data[:8] + chunk(b"tEXt", b"k\x00" + b"\x00" * 20) + data[8:]
    assert cv2.imdecode(np.frombuffer(moved, np.uint8), cv2.IMREAD_COLOR) is None
    with pytest.raises(DataError, match=r"x\.png: damaged PNG header \(.*IHDR"):
        read_header(moved, "x.png")


@pytest.mark.parametrize(("width", "height"), [(0, 4), (4, 0), (2**31, 4), (4, 2**32 - 1)])
def test_a_png_size_libpng_would_refuse_is_a_damaged_header(width, height):
    data = bytearray(png())
    ihdr = struct.pack(">II", width, height) + bytes(data[24:29])
    data[16:33] = ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    assert cv2.imdecode(np.frombuffer(bytes(data), np.uint8), cv2.IMREAD_COLOR) is None
    with pytest.raises(DataError, match=r"damaged PNG header \(its (width|height) is"):
        read_header(bytes(data), "x.png")


def test_other_formats_have_no_header_read():
    bmp = cv2.imencode(".bmp", np.zeros((3, 3, 3), np.uint8))[1].tobytes()
    assert read_header(bmp, "x.bmp") is None
    assert read_header(b"", "x") is None


@pytest.mark.parametrize(
    "params",
    [
        [],
        [cv2.IMWRITE_JPEG_PROGRESSIVE, 1],
        [cv2.IMWRITE_JPEG_OPTIMIZE, 1],
        [cv2.IMWRITE_JPEG_RST_INTERVAL, 2],
        [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420],
    ],
)
@pytest.mark.parametrize(("height", "width", "channels"), [(1, 9, 3), (17, 5, 1), (33, 64, 3)])
def test_the_size_read_is_the_size_opencv_decodes(params, height, width, channels):
    pixels = np.random.default_rng(1).integers(0, 256, (height, width, channels), dtype=np.uint8)
    for extension, options in ((".jpg", params), (".png", [])):
        image = pixels[:, :, 0] if channels == 1 else pixels
        data = cv2.imencode(extension, image, options)[1].tobytes()
        header = read_header(data, "x")
        assert (header.width, header.height) == decoded_size(data) == (width, height)


# 20 MB header bodies that cost a marker-by-marker reader one Python step per few
# bytes (seconds holding the GIL in the service's threadpool).
CPU_TRAPS = {
    "4-byte COM segments": b"\xff\xfe\x00\x02" * 5_000_000,
    "TEM markers": b"\xff\x01" * 10_000_000,
    "stuffed zeros (FF 00)": b"\xff\x00" * 10_000_000,
    "fill bytes": b"\xff" * 20_000_000,
    "bytes between segments": b"\x00" * 20_000_000,
}


@pytest.mark.parametrize("body", list(CPU_TRAPS.values()), ids=list(CPU_TRAPS))
def test_a_header_built_to_burn_cpu_is_answered_at_once(body):
    crafted = JPEG_START + body + jpeg()[2:]
    started = time.perf_counter()
    try:
        header = read_header(crafted, "x.jpg")
    except DataError as refused:
        assert str(refused).startswith("x.jpg: damaged JPEG header (")
    else:  # what libjpeg decodes: the real frame after the skipped bytes
        assert header == ImageHeader("jpeg", 64, 48)
    seconds = time.perf_counter() - started
    assert seconds < 2, f"{seconds:.1f} s"  # well under 0.5 s; 2 for a busy CI


def test_more_markers_before_the_frame_header_than_a_camera_writes_are_refused():
    real = jpeg()
    # 255 ICC chunks (APP2, the most a profile may be split into) are read past.
    icc = b"".join(segment(0xE2, b"ICC_PROFILE\x00" + bytes([n, 255]) + b"p") for n in range(255))
    assert read_header(real[:2] + icc + real[2:], "x.jpg") == ImageHeader("jpeg", 64, 48)
    comments = segment(COM, b"c") * 1100
    with pytest.raises(DataError, match=r"^x\.jpg: damaged JPEG header \(more than 1024 markers"):
        read_header(real[:2] + comments + real[2:], "x.jpg")
