"""Lifting keypoints with depth inverts projection; missing depth gives NaN."""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.core.camera import SEVENSCENES_DEFAULT
from relocfw.core.errors import DataError
from relocfw.structure.lifting import lift_keypoints
from tests.structure.scenes import points_in_view, random_pose, to_camera

CAMERA = SEVENSCENES_DEFAULT


def depth_map_of(pixels: np.ndarray, depths: np.ndarray, width: int, height: int) -> np.ndarray:
    """A NaN depth map holding each point's depth at its nearest pixel."""
    depth = np.full((height, width), np.nan, dtype=np.float32)
    depth[np.floor(pixels[:, 1] + 0.5).astype(int), np.floor(pixels[:, 0] + 0.5).astype(int)] = (
        depths
    )
    return depth


def test_lifting_inverts_projection():
    rng = np.random.default_rng(0)
    pose = random_pose(rng)
    # Sub-pixel keypoints over the whole image, one per depth pixel at most.
    pixels, world = points_in_view(rng, CAMERA, pose, 200)
    keep = np.unique(np.floor(pixels + 0.5).astype(int), axis=0, return_index=True)[1]
    pixels, world = pixels[keep], world[keep]
    depth = depth_map_of(pixels, to_camera(pose, world)[:, 2], CAMERA.width, CAMERA.height)
    lifted = lift_keypoints(pixels, depth, CAMERA, pose)
    assert np.allclose(CAMERA.project(to_camera(pose, lifted)), pixels, atol=1e-9)
    assert np.abs(lifted - world).max() < 1e-6  # float32 depth: ~1e-7 of 4 m


def test_a_depth_map_at_another_resolution_is_read_at_the_scaled_pixel():
    pose = random_pose(np.random.default_rng(1))
    # Depth varies by column so the wrong pixel would give the wrong depth.
    low = np.tile(np.arange(1, 321, dtype=np.float32) * 0.01, (240, 1))  # 320 x 240
    keypoints = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [639.0, 479.0], [320.4, 10.0]])
    lifted = lift_keypoints(keypoints, low, CAMERA, pose)
    z = to_camera(pose, lifted)[:, 2]
    # x -> (x + 0.5) / 2 - 0.5 rounded: 0 -> -0.25 -> 0; 1 -> 0.25 -> 0; 2 -> 0.75 -> 1;
    # 639 -> 319.25 -> 319; 320.4 -> 159.95 -> 160.
    assert np.allclose(z, np.array([1, 1, 2, 320, 161]) * 0.01, atol=1e-6)


def test_missing_depth_and_points_outside_the_map_give_nan():
    pose = random_pose(np.random.default_rng(2))
    depth = np.full((480, 640), 2.0, dtype=np.float32)
    depth[10, 20] = np.nan  # read_depth's "no reading"
    depth[30, 40] = 0.0  # a raw map's "no reading"
    keypoints = np.array([[20.0, 10.0], [40.0, 30.0], [-3.0, 5.0], [100.0, 480.0], [5.0, 5.0]])
    lifted = lift_keypoints(keypoints, depth, CAMERA, pose)
    assert np.isnan(lifted[:4]).all()
    assert np.isfinite(lifted[4]).all()
    assert np.isclose(to_camera(pose, lifted[4:])[0, 2], 2.0)


def test_no_keypoints_give_an_empty_array():
    lifted = lift_keypoints(
        np.zeros((0, 2)), np.ones((480, 640)), CAMERA, random_pose(np.random.default_rng(3))
    )
    assert lifted.shape == (0, 3)


@pytest.mark.parametrize(
    "keypoints, depth, message",
    [
        (np.zeros((3, 3)), np.ones((4, 4)), "keypoints must be an \\[N, 2\\]"),
        (np.full((3, 2), np.nan), np.ones((4, 4)), "keypoints has 3 rows with NaN"),
        (np.zeros((3, 2)), np.ones((4, 4, 3)), "depth must be a non-empty \\[H, W\\]"),
        (np.zeros((3, 2)), np.ones((0, 4)), "depth must be a non-empty \\[H, W\\]"),
    ],
)
def test_malformed_inputs_raise_one_data_error(keypoints, depth, message):
    with pytest.raises(DataError, match=message):
        lift_keypoints(keypoints, depth, CAMERA, random_pose(np.random.default_rng(4)))
