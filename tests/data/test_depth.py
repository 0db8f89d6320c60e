"""Reading 7-Scenes depth maps: millimetres to metres, no reading to NaN, bad files named."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.values import Pose
from relocfw.data.depth import (
    TUM_UNITS_PER_METRE,
    depth_path_of,
    encode_depth,
    read_depth,
    read_frame_depth,
    write_depth,
)
from relocfw.data.frames import Frame

REDKITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "7scenes-redkitchen"


def write_png(tmp_path: Path, pixels: np.ndarray, name: str = "frame-000000.depth.png") -> Path:
    path = tmp_path / name
    assert cv2.imwrite(str(path), pixels)
    return path


def test_millimetres_become_metres_and_no_reading_becomes_nan(tmp_path):
    raw = np.array([[0, 1, 1000], [2500, 65535, 65534]], dtype=np.uint16)
    depth = read_depth(write_png(tmp_path, raw), expected_size=(3, 2))
    assert depth.dtype == np.float32 and depth.shape == (2, 3)
    assert np.isnan(depth[0, 0]) and np.isnan(depth[1, 1])
    assert np.allclose(depth[[0, 0, 1, 1], [1, 2, 0, 2]], [0.001, 1.0, 2.5, 65.534])


def test_reads_a_real_red_kitchen_depth_map():
    path = REDKITCHEN / "redkitchen" / "seq-01" / "frame-000000.depth.png"
    if not path.is_file():
        pytest.skip(f"Red Kitchen not found at {REDKITCHEN}")
    depth = read_depth(path, expected_size=(640, 480))
    assert depth.shape == (480, 640)
    assert 0.02 < np.isnan(depth).mean() < 0.3  # the README: about 8% without a reading
    assert 0.5 < np.nanmedian(depth) < 4.0  # a kitchen, in metres


@pytest.mark.parametrize(
    "pixels, message",
    [
        (
            np.zeros((4, 6), dtype=np.uint8),
            "single-channel 16-bit .* found 1 channel\\(s\\) of uint8",
        ),
        (np.zeros((4, 6, 3), dtype=np.uint16), "found 3 channel\\(s\\) of uint16"),
        (np.zeros((5, 6), dtype=np.uint16), "depth map is 6x5, expected 6x4"),
    ],
)
def test_a_wrong_image_is_one_data_error_naming_the_file(tmp_path, pixels, message):
    path = write_png(tmp_path, pixels)
    with pytest.raises(DataError, match=message) as error:
        read_depth(path, expected_size=(6, 4))
    assert str(path) in str(error.value)


def test_a_missing_empty_or_corrupt_file_is_one_data_error_naming_it(tmp_path):
    missing = tmp_path / "frame-000001.depth.png"
    with pytest.raises(DataError, match=f"depth map not found: {missing}"):
        read_depth(missing)
    for name, content in (("empty.png", b""), ("corrupt.png", b"\x89PNG\r\n\x1a\n garbage")):
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(DataError, match=f"cannot decode depth map .*: {path}"):
            read_depth(path)


@pytest.mark.parametrize("size", [(640,), (640, 0), (640.0, 480), "640x480"])
def test_an_impossible_expected_size_is_a_config_error(tmp_path, size):
    path = write_png(tmp_path, np.zeros((4, 6), dtype=np.uint16))
    with pytest.raises(ConfigError, match="expected_size"):
        read_depth(path, expected_size=size)


@pytest.mark.parametrize(
    "image, depth",
    [
        ("seq-01/frame-000000.color.jpg", "seq-01/frame-000000.depth.png"),
        ("seq-01/frame-000123.color.png", "seq-01/frame-000123.depth.png"),
    ],
)
def test_the_depth_map_beside_a_colour_image(image, depth):
    assert depth_path_of(Path(image)) == Path(depth)


def test_a_name_that_is_not_7scenes_is_one_data_error():
    with pytest.raises(DataError, match="image.jpg: not a 7-Scenes colour image name"):
        depth_path_of("seq-01/image.jpg")


def test_tum_depth_is_read_at_5000_per_metre(tmp_path):
    raw = np.array([[0, 5000, 12500]], dtype=np.uint16)
    depth = read_depth(write_png(tmp_path, raw), units_per_metre=TUM_UNITS_PER_METRE)
    assert np.isnan(depth[0, 0]) and np.allclose(depth[0, 1:], [1.0, 2.5])


@pytest.mark.parametrize("scale", [0, -1000, float("nan"), float("inf"), "1000", True])
def test_an_impossible_scale_is_a_config_error(tmp_path, scale):
    path = write_png(tmp_path, np.zeros((4, 6), dtype=np.uint16))
    with pytest.raises(ConfigError, match="units_per_metre must be a positive number"):
        read_depth(path, units_per_metre=scale)


def test_written_depth_reads_back_to_the_nearest_unit(tmp_path):
    metres = np.array([[1.2344, 0.0, np.nan], [np.inf, 65.6, 2.0]])
    assert np.array_equal(encode_depth(metres), [[1234, 0, 0], [0, 0, 2000]])
    path = tmp_path / "frame-000000.depth.png"
    write_depth(path, metres, units_per_metre=5000.0)
    read_back = read_depth(path, (3, 2), units_per_metre=5000.0)
    assert read_back[0, 0] == pytest.approx(1.2344) and read_back[1, 2] == pytest.approx(2.0)
    # No reading, zero, beyond 16 bits (65.6 m x 5000): all NaN when read back.
    assert np.isnan(read_back[[0, 0, 1, 1], [1, 2, 0, 1]]).all()


def test_a_frame_without_depth_gives_none_and_one_with_the_wrong_size_names_it(tmp_path):
    pose = Pose([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    camera = PinholeCamera(5.0, 5.0, 2.5, 1.5, 6, 4)
    assert read_frame_depth(Frame("a", tmp_path / "a.png", pose, camera)) is None
    path = write_png(tmp_path, np.full((5, 6), 1000, dtype=np.uint16))
    with pytest.raises(DataError, match="depth map is 6x5, expected 6x4") as error:
        read_frame_depth(Frame("a", tmp_path / "a.png", pose, camera, path))
    assert str(path) in str(error.value)
    # Without a camera there is no size to hold it to.
    assert read_frame_depth(Frame("a", tmp_path / "a.png", pose, None, path)).shape == (5, 6)
