"""The pinhole camera: checked on creation, its matrix, resizing and projection."""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.core.camera import SEVENSCENES_DEFAULT, PinholeCamera
from relocfw.core.errors import ConfigError, DataError


def test_the_7scenes_camera_and_its_matrix():
    camera = SEVENSCENES_DEFAULT
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (585.0, 585.0, 320.0, 240.0)
    assert (camera.width, camera.height) == (640, 480)
    assert np.array_equal(camera.matrix(), [[585, 0, 320], [0, 585, 240], [0, 0, 1]])


def test_equal_cameras_from_numpy_numbers_compare_equal():
    made = PinholeCamera(np.float32(585), 585, np.int64(320), 240.0, np.int64(640), 480)
    assert made == SEVENSCENES_DEFAULT and hash(made) == hash(SEVENSCENES_DEFAULT)


@pytest.mark.parametrize(
    "values, name",
    [
        ((0, 585, 320, 240, 640, 480), "fx"),
        ((585, -1, 320, 240, 640, 480), "fy"),
        ((585, 585, float("nan"), 240, 640, 480), "cx"),
        ((585, 585, 320, float("inf"), 640, 480), "cy"),
        ((585, 585, 320, 240, 0, 480), "width"),
        ((585, 585, 320, 240, 640, 480.5), "height"),
        ((585, 585, 320, 240, True, 480), "width"),
        (("a", 585, 320, 240, 640, 480), "fx"),
    ],
)
def test_a_bad_value_raises_a_config_error_naming_it(values, name):
    with pytest.raises(ConfigError, match=f"camera {name}"):
        PinholeCamera(*values)


def test_projection_of_points_in_front_and_behind():
    camera = PinholeCamera(500.0, 400.0, 300.0, 200.0, 600, 400)
    points = np.array([[0.0, 0.0, 2.0], [1.0, -1.0, 2.0], [0.0, 0.0, 0.0], [1.0, 1.0, -1.0]])
    pixels = camera.project(points)
    assert np.array_equal(pixels[:2], [[300.0, 200.0], [550.0, 0.0]])
    assert np.isnan(pixels[2:]).all()  # on or behind the camera plane: no pixel
    with pytest.raises(DataError, match="points_camera must be an \\[N, 3\\]"):
        camera.project(np.zeros((4, 2)))


def test_scaling_maps_pixel_edges_onto_pixel_edges():
    camera = SEVENSCENES_DEFAULT
    half = camera.scaled_to(320, 240)
    assert (half.width, half.height, half.fx, half.fy) == (320, 240, 292.5, 292.5)
    assert (half.cx, half.cy) == (159.75, 119.75)
    # A point's pixel in the resized image is its pixel in the original, mapped as
    # cv2.resize maps coordinates: x' = (x + 0.5) * s - 0.5.
    points = np.random.default_rng(0).uniform([-1, -1, 1], [1, 1, 4], (20, 3))
    expected = (camera.project(points) + 0.5) * 0.5 - 0.5
    assert np.allclose(half.project(points), expected)
    assert camera.scaled_to(640, 480) == camera
    with pytest.raises(ConfigError, match="width"):
        camera.scaled_to(0, 240)
