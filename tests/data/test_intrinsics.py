"""Reading 7-Scenes' camera-intrinsics.txt: good files read right, bad ones named."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from relocfw.core.camera import SEVENSCENES_DEFAULT, PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.data.intrinsics import (
    read_camera_for_images,
    read_intrinsics_matrix,
    write_intrinsics_matrix,
)

REDKITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "7scenes-redkitchen"
# 7-Scenes' own layout: 18-digit mantissas, exponents, a newline after each row.
SEVENSCENES_TEXT = (
    "5.850000000000000000e+02 0.000000000000000000e+00 3.200000000000000000e+02\n"
    "0.000000000000000000e+00 5.850000000000000000e+02 2.400000000000000000e+02\n"
    "0.000000000000000000e+00 0.000000000000000000e+00 1.000000000000000000e+00\n"
)


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "camera-intrinsics.txt"
    path.write_text(text)
    return path


def test_reads_the_7scenes_format(tmp_path):
    camera = read_intrinsics_matrix(write(tmp_path, SEVENSCENES_TEXT), 640, 480)
    assert camera == SEVENSCENES_DEFAULT


def test_reads_tabs_crlf_comments_and_another_camera(tmp_path):
    text = "# K of a test camera\r\n500\t0\t310.5\r\n\r\n0\t520\t250\r\n0\t0\t1\r\n"
    camera = read_intrinsics_matrix(write(tmp_path, text), 600, 500)
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (500, 520, 310.5, 250)
    assert (camera.width, camera.height) == (600, 500)


def test_reads_the_real_red_kitchen_file():
    path = REDKITCHEN / "camera-intrinsics.txt"
    if not path.is_file():
        pytest.skip(f"Red Kitchen not found at {REDKITCHEN}")
    assert read_intrinsics_matrix(path, 640, 480) == SEVENSCENES_DEFAULT


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "expected a 3x3 matrix \\(3 rows of 3 numbers\\), found 0"),
        ("585 0 320\n0 585 240\n", "found 2"),
        (SEVENSCENES_TEXT + "0 0 1\n", ":4: a 3x3 matrix has 3 rows"),
        ("585 0 320\n0 585\n0 0 1\n", ":2: expected 3 values, found 2"),
        ("585 0 320\n0 585 240 1\n0 0 1\n", ":2: expected 3 values, found 4"),
        ("585 0 320\n0 five 240\n0 0 1\n", ":2: not a number"),
        ("585 0 nan\n0 585 240\n0 0 1\n", ":1: NaN or infinite"),
        ("585 0.5 320\n0 585 240\n0 0 1\n", ":1: skew K\\[0,1\\] = 0.5"),
        ("585 0 320\n2 585 240\n0 0 1\n", ":2: K\\[1,0\\] = 2"),
        ("585 0 320\n0 585 240\n0 0 2\n", ":3: bottom row must be 0 0 1, got 0 0 2"),
        ("585 0 320\n0 585 240\n0.1 0 1\n", ":3: bottom row must be 0 0 1"),
        ("-585 0 320\n0 585 240\n0 0 1\n", ":1: focal length fx = -585"),
        ("585 0 320\n0 0 240\n0 0 1\n", ":2: focal length fy = 0"),
    ],
)
def test_each_bad_file_is_one_data_error_naming_it(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(DataError, match=message) as error:
        read_intrinsics_matrix(path, 640, 480)
    assert str(path) in str(error.value)


def test_a_missing_or_binary_file_is_one_data_error_naming_it(tmp_path):
    missing = tmp_path / "nowhere.txt"
    with pytest.raises(DataError, match=f"file not found: {missing}"):
        read_intrinsics_matrix(missing, 640, 480)
    binary = tmp_path / "binary.txt"
    binary.write_bytes(b"\xff\xfe\x00\x81" * 10)
    with pytest.raises(DataError, match=f"{binary}: not a text file"):
        read_intrinsics_matrix(binary, 640, 480)


def test_an_impossible_image_size_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="camera width"):
        read_intrinsics_matrix(write(tmp_path, SEVENSCENES_TEXT), 0, 480)


def write_image(path: Path, width: int, height: int) -> Path:
    assert cv2.imwrite(str(path), np.zeros((height, width, 3), dtype=np.uint8))
    return path


def test_the_size_comes_from_the_first_image_that_decodes(tmp_path):
    corrupt = tmp_path / "a.png"
    corrupt.write_bytes(b"not a png")
    images = [
        corrupt,
        write_image(tmp_path / "b.png", 64, 40),
        write_image(tmp_path / "c.png", 8, 8),
    ]
    camera = read_camera_for_images(write(tmp_path, SEVENSCENES_TEXT), images)
    assert camera == PinholeCamera(585, 585, 320, 240, 64, 40)


def test_a_malformed_file_is_named_before_any_image_is_read(tmp_path):
    path = write(tmp_path, "585 0 320\n0 585 240\n")
    with pytest.raises(DataError, match="found 2") as error:
        read_camera_for_images(path, [tmp_path / "missing.png"])
    assert str(path) in str(error.value)


def test_no_image_that_decodes_is_one_data_error(tmp_path):
    missing = tmp_path / "missing.png"
    with pytest.raises(DataError, match=f"no image decodes.*first: {missing}"):
        read_camera_for_images(write(tmp_path, SEVENSCENES_TEXT), [missing])


def test_a_written_matrix_reads_back_exactly(tmp_path):
    camera = PinholeCamera(43.875, 44.1, 23.5, 17.5, 48, 36)
    path = tmp_path / "camera-intrinsics.txt"
    write_intrinsics_matrix(path, camera)
    assert read_intrinsics_matrix(path, 48, 36) == camera
    assert path.read_text().splitlines()[2] == SEVENSCENES_TEXT.splitlines()[2]
