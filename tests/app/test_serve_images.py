"""Thin images sent to the service: refused by relocfw.serve.images.decode_image on
their header, in one line naming query.max_aspect, and answered over HTTP as a 400
JSON, never a plain-text 500 from an allocation deep in the strip."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from relocfw.core.errors import DataError
from relocfw.serve.images import decode_image
from tests.app.test_serve_helpers import (
    MAX_BYTES,
    MAX_PIXELS,
    png_of,
    running,
    serve_command,
    tiny_model,
)


def thin_png(width: int) -> bytes:
    return cv2.imencode(".png", np.full((1, width, 3), 90, np.uint8))[1].tobytes()


@pytest.mark.parametrize("width", [5000, 300000])
def test_decode_image_refuses_a_thin_png_on_its_header(width):
    body = thin_png(width)
    assert len(body) < 1500
    with pytest.raises(DataError) as refused:
        decode_image(body, max_pixels=MAX_PIXELS)
    message = str(refused.value)
    assert message.startswith(f"the request body: its header announces {width} x 1 pixels")
    assert "more than query.max_aspect=10 allows" in message and "\n" not in message
    # A raised limit lets it through to the pixels, which are checked again.
    assert decode_image(body, MAX_PIXELS, max_aspect=width).shape == (1, width, 3)


def test_decode_image_checks_the_pixels_too(monkeypatch):
    import relocfw.serve.images as images

    monkeypatch.setattr(images, "check_header", lambda *_: None)  # as if no header were read
    monkeypatch.setattr(images, "check_pixels", lambda *_: None)
    with pytest.raises(DataError, match=r"^the request body is 5000 x 1 pixels, .*max_aspect"):
        decode_image(thin_png(5000), MAX_PIXELS)


def test_decode_image_turns_an_allocation_failure_into_a_data_error(monkeypatch):
    import relocfw.serve.images as images

    def out_of_memory(*_):
        raise MemoryError

    monkeypatch.setattr(images.cv2, "imdecode", out_of_memory)
    with pytest.raises(DataError, match=r"^the request body: out of memory decoding it; .*pixels"):
        decode_image(png_of(np.zeros((4, 4, 3), np.uint8)), MAX_PIXELS)


def jpeg_of(pixels: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", pixels)[1].tobytes()


FRAME = np.random.default_rng(3).integers(0, 256, (36, 48, 3), dtype=np.uint8)
# What phones write after a JPEG's end: a Pixel Motion Photo's MP4, a Samsung trailer.
MOTION_PHOTO = jpeg_of(FRAME) + b"\x00\x00\x00\x18ftypmp42\x00\x00\x00\x00" + bytes(range(256))
SAMSUNG_TRAILER = (
    jpeg_of(FRAME) + b"\x00\x00\x0a\x01\xff\xd8 data" + b"SEFH" + b"\x01" * 20 + b"SEFT"
)


@pytest.mark.parametrize("body", [MOTION_PHOTO, SAMSUNG_TRAILER], ids=["motion", "samsung"])
def test_a_jpeg_with_bytes_after_its_end_is_decoded(body):
    assert cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR).shape == (36, 48, 3)
    assert decode_image(body, MAX_PIXELS).shape == (36, 48, 3)


def test_a_jpeg_cut_inside_its_scan_is_still_refused_as_truncated():
    whole = jpeg_of(FRAME)
    progressive = cv2.imencode(".jpg", FRAME, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    cut = progressive.rindex(b"\xff\xda")  # a progressive file cut before its last scan
    for body in (whole[:-2], whole[: len(whole) - 40], whole[:-2] + b"trailing", progressive[:cut]):
        with pytest.raises(DataError, match=r"^the request body is a truncated JPEG"):
            decode_image(body, MAX_PIXELS)


def test_the_service_answers_thin_images_with_a_400_json(tmp_path):
    model = tiny_model(tmp_path)
    overrides = [f"serve.max_bytes={MAX_BYTES}", f"serve.max_pixels={MAX_PIXELS}"]
    (tmp_path / "serve").mkdir()
    command = serve_command(model, *overrides)
    with running(command, tmp_path / "serve") as server, server.client() as client:
        for width in (5000, 300000):
            answer = client.post(
                "/v1/localize", content=thin_png(width), headers={"Content-Type": "image/png"}
            )
            assert answer.status_code == 400, answer.text
            assert answer.headers["content-type"] == "application/json"
            assert "query.max_aspect=10" in answer.json()["error"]
        good = png_of(np.zeros((36, 48, 3), np.uint8))
        answer = client.post("/v1/localize", content=good, headers={"Content-Type": "image/png"})
        assert answer.status_code == 200, answer.text
        headers = {"Content-Type": "image/jpeg"}
        answer = client.post("/v1/localize", content=MOTION_PHOTO, headers=headers)
        assert answer.status_code == 200, answer.text


def test_the_service_checks_headers_against_the_query_max_aspect_it_runs_with(tmp_path):
    """query.max_aspect raised for the service reaches its header check, not only the
    pipeline: a 15:1 PNG is answered at query.max_aspect=20 and refused at the default."""
    model = tiny_model(tmp_path)
    wide = png_of(np.zeros((4, 60, 3), np.uint8))
    (tmp_path / "serve").mkdir()
    command = serve_command(model, "query.max_aspect=20")
    with running(command, tmp_path / "serve") as server, server.client() as client:
        answer = client.post("/v1/localize", content=wide, headers={"Content-Type": "image/png"})
        assert answer.status_code == 200, answer.text
