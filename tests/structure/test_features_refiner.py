"""refine=features' options and the cache key of its map structure."""

from __future__ import annotations

import os

import numpy as np
import pytest

from relocfw import ConfigError, MapImage, Pose
from relocfw.plugins.features_refiner import FeaturesRefiner


@pytest.mark.parametrize(
    "options, message",
    [
        ({"ratio": 2.0}, "refine.ratio must be above 0 and at most 1, got 2.0"),
        ({"ratio": "abc"}, "refine.ratio must be a number, got 'abc'"),
        ({"max_error_px": -1}, "refine.max_error_px must be above 0, got -1"),
        ({"count": 0}, "refine.count must be at least 1, got 0"),
        ({"structure": "lidar"}, "refine.structure must be one of depth, triangulated"),
        ({"keyframes": "random"}, "refine.keyframes must be one of descriptor, pose, track"),
    ],
)
def test_a_bad_option_is_refused_when_built_naming_its_key(options, message):
    with pytest.raises(ConfigError) as caught:
        FeaturesRefiner(**options)
    assert str(caught.value).startswith(message)


def test_the_cache_key_sees_pixels_and_depth_files(tmp_path):
    depth = tmp_path / "frame.depth.png"
    depth.write_bytes(b"first")
    image = np.zeros((4, 6, 3), dtype=np.uint8)
    pose = Pose(np.zeros(3), np.array([1.0, 0, 0, 0]))
    view = MapImage("frame", image, pose, None, depth)
    refiner = FeaturesRefiner()
    before = refiner.settings([view])
    assert refiner.settings([view]) == before
    other_pixels = image.copy()
    other_pixels[0, 0, 0] = 1
    assert refiner.settings([MapImage("frame", other_pixels, pose, None, depth)]) != before
    depth.write_bytes(b"second, longer")  # a re-made depth map
    os.utime(depth, ns=(1, 1))
    changed = refiner.settings([view])
    assert changed != before
    depth.unlink()
    assert refiner.settings([view]) not in (before, changed)
    tum_scale = MapImage("frame", image, pose, None, depth, depth_units_per_metre=5000.0)
    assert refiner.settings([tum_scale]) != refiner.settings([view])
