"""A map view is checked once, when it is made."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from relocfw.core.camera import SEVENSCENES_DEFAULT
from relocfw.core.errors import DataError
from relocfw.core.values import Pose
from relocfw.structure.map_view import MapView

IMAGE = np.zeros((480, 640, 3), np.uint8)
POSE = Pose([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])


def test_a_view_keeps_its_values_and_makes_the_depth_path_a_path():
    view = MapView(IMAGE, POSE, SEVENSCENES_DEFAULT, "frame.depth.png", "seq-01/frame-0")
    assert view.depth_path == Path("frame.depth.png")
    assert view.image is IMAGE  # not copied: a map holds hundreds of images
    assert "seq-01/frame-0" in repr(view) and len(repr(view)) < 200
    assert MapView(IMAGE, POSE, SEVENSCENES_DEFAULT).depth_path is None


def test_wrong_parts_are_named():
    with pytest.raises(DataError, match="'a'.*320x240 but its camera is 640x480"):
        MapView(IMAGE[::2, ::2], POSE, SEVENSCENES_DEFAULT, None, "a")
    with pytest.raises(DataError, match="'b' has dtype float"):
        MapView(IMAGE / 255.0, POSE, SEVENSCENES_DEFAULT, None, "b")
    with pytest.raises(DataError, match="pose must be a Pose"):
        MapView(IMAGE, np.eye(4), SEVENSCENES_DEFAULT, None, "c")
    with pytest.raises(DataError, match="camera must be a PinholeCamera"):
        MapView(IMAGE, POSE, (585, 585, 320, 240), None, "d")
    with pytest.raises(DataError, match="depth_path must be a path"):
        MapView(IMAGE, POSE, SEVENSCENES_DEFAULT, 3, "e")
    with pytest.raises(DataError, match="depth_units_per_metre must be a positive number"):
        MapView(IMAGE, POSE, SEVENSCENES_DEFAULT, None, "f", depth_units_per_metre=0)
    with pytest.raises(DataError, match="name must be a string"):
        MapView(IMAGE, POSE, SEVENSCENES_DEFAULT, None, 7)
