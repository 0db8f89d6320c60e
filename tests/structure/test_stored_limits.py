"""A stored map or refiner state holds only values a query can work with: every
size-like option has an upper bound and every camera is plausible (finite, focal
lengths and sizes within reach of a real camera, the principal point near its
image), each refusal naming the file or tensor and the key."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from relocfw.core.camera import SEVENSCENES_COLOUR
from relocfw.core.errors import DataError
from relocfw.structure.compact_map import CompactMap
from relocfw.structure.compact_writer import save_compact_map
from relocfw.structure.map_state import camera_of_row
from relocfw.structure.refiner_state import STATE_LABEL, options_state, stored_options

GOOD_OPTIONS = {
    "keyframes": "descriptor",
    "count": 10,
    "max_features": 1024,
    "min_inliers": 12,
    "ransac_min_iterations": 100,
    "ratio": 0.8,
    "max_error_px": 8.0,
    "image_scale": 1.0,
}


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("max_features", 2**40),
        ("count", 2**40),
        ("min_inliers", 2**40),
        ("max_error_px", 1e300),
    ],
)
def test_a_size_like_option_far_above_any_use_is_refused_naming_it(key, value):
    state = options_state(GOOD_OPTIONS)
    assert stored_options(state)[key] == GOOD_OPTIONS[key]
    state[key] = torch.tensor(value, dtype=state[key].dtype)
    with pytest.raises(DataError, match=rf"^{STATE_LABEL}: refine\.{key} must be at most"):
        stored_options(state)


CAMERA_ROW = [525.0, 525.0, 320.0, 240.0, 640.0, 480.0]


@pytest.mark.parametrize(
    ("column", "value", "key"),
    [
        (2, 1e300, "cx"),
        (3, -1e6, "cy"),
        (4, 1e15, "width"),
        (5, 200_000.0, "height"),
        (0, 1e300, "fx"),
    ],
)
def test_an_implausible_camera_in_a_compact_map_is_refused_naming_the_file(
    depth_structure, tmp_path, column, value, key
):
    save_compact_map(depth_structure, tmp_path / "map")
    assert CompactMap.open(tmp_path / "map").camera(0) == depth_structure.cameras[0]
    path = tmp_path / "map" / "cameras.npy"
    cameras = np.load(path)
    cameras[1, column] = value
    np.save(path, cameras)  # the same size: map.json's record still holds
    with pytest.raises(DataError, match=rf"cameras\.npy: camera 1 .*\b{key}\b") as caught:
        CompactMap.open(tmp_path / "map")
    assert str(caught.value).startswith(str(tmp_path / "map"))


@pytest.mark.parametrize(("column", "value", "key"), [(2, 1e300, "cx"), (4, 1e15, "width")])
def test_an_implausible_camera_in_a_stored_map_is_refused_naming_it(column, value, key):
    row = np.array(CAMERA_ROW)
    assert camera_of_row(row, 3, "model.relocfw") == SEVENSCENES_COLOUR
    row[column] = value
    with pytest.raises(DataError, match=rf"^model\.relocfw: cameras\[3\]: .*\b{key}\b"):
        camera_of_row(row, 3, "model.relocfw")
