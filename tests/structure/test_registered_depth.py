"""Depth registered to the colour camera: a depth sensor beside the colour camera, with
its own focal length, lifts colour keypoints to their own surface points.

The world is tests.structure.textured_world (exact depth at every pixel centre, exact
surface points for sub-pixel keypoints); the depth sensor sits 2.5 cm along x of the
colour camera, turned by 1 degree, with a longer focal length, as a Kinect's does.
"""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.core.camera import SEVENSCENES_COLOUR, SEVENSCENES_DEPTH, PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import matrix_to_quaternion, quaternion_to_matrix
from relocfw.core.rigid import checked_rigid
from relocfw.core.values import Pose
from relocfw.data.sevenscenes import (
    SEVENSCENES_DEPTH_TO_COLOUR,
    SevenScenes,
    load_sevenscenes,
)
from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.map_view import MapView
from relocfw.structure.registration import register_depth
from relocfw.structure.structure_cache import structure_key
from tests.structure.textured_world import (
    depth_map,
    looking_at,
    make_world,
    render,
    surface_points,
    write_depth_png,
)

COLOUR = PinholeCamera(262.5, 262.5, 159.5, 119.5, 320, 240)  # 7-Scenes' 525 at half size
DEPTH = PinholeCamera(292.5, 292.5, 159.5, 119.5, 320, 240)  # and its 585


def depth_to_colour(offset_m: float = -0.025, degrees: float = 1.0) -> np.ndarray:
    """x_colour = R x_depth + t: a turn about y and a shift along x."""
    angle = np.radians(degrees)
    transform = np.eye(4)
    transform[:3, :3] = [
        [np.cos(angle), 0.0, np.sin(angle)],
        [0.0, 1.0, 0.0],
        [-np.sin(angle), 0.0, np.cos(angle)],
    ]
    transform[:3, 3] = [offset_m, 0.0, 0.0]
    return transform


def depth_sensor_pose(colour_pose: Pose, transform: np.ndarray) -> Pose:
    """The depth sensor's camera-to-world pose: world = P_colour T x_depth."""
    colour = np.eye(4)
    colour[:3, :3] = quaternion_to_matrix(colour_pose.quaternion)
    colour[:3, 3] = colour_pose.position
    sensor = colour @ transform
    return Pose(sensor[:3, 3], matrix_to_quaternion(sensor[:3, :3]))


@pytest.fixture(scope="module")
def kinect_view(tmp_path_factory):
    """A colour image, its raw depth PNG from the depth sensor, and the truth."""
    world = make_world(seed=3)
    pose = looking_at([0.1, -0.1, 0.0], [0.0, 0.1, 3.0])
    transform = depth_to_colour()
    raw = depth_map(world, depth_sensor_pose(pose, transform), DEPTH)
    path = write_depth_png(raw, tmp_path_factory.mktemp("kinect") / "frame.depth.png")
    return world, pose, transform, raw, path


def lifting_errors(kinect_view, depth: np.ndarray, count: int = 400) -> np.ndarray:
    """Distances (m) from sub-pixel colour keypoints lifted with `depth` to their true
    surface points; NaN where the keypoint has no depth."""
    world, pose, _, _, _ = kinect_view
    rng = np.random.default_rng(0)
    keypoints = rng.uniform([20, 20], [COLOUR.width - 21, COLOUR.height - 21], (count, 2))
    truth = surface_points(world, pose, COLOUR, keypoints)
    lifted = lift_keypoints(keypoints, depth, COLOUR, pose)
    return np.linalg.norm(lifted - truth, axis=1)


def test_registered_depth_lifts_keypoints_to_their_surface_points(kinect_view):
    _, _, transform, raw, _ = kinect_view
    registered = register_depth(raw, DEPTH, COLOUR, transform)
    errors = lifting_errors(kinect_view, registered)
    found = errors[np.isfinite(errors)]
    assert len(found) > 0.9 * len(errors)
    # Within 1 cm, but for keypoints on a depth edge (the nearest reading may be the
    # other surface's).
    assert np.mean(found < 0.01) > 0.9
    assert np.median(found) < 0.003
    # Reading the raw map at the colour pixel (what lifting did before) is far worse:
    # the longer focal length and the offset move every reading.
    unregistered = lifting_errors(kinect_view, raw)
    assert np.nanmedian(unregistered) > 0.01
    assert np.nanmedian(unregistered) > 10 * np.median(found)
    assert np.nanmean(unregistered < 0.01) < 0.5


def test_the_map_builder_registers_a_view_with_a_depth_camera(kinect_view):
    world, pose, transform, _, path = kinect_view
    image = render(world, pose, COLOUR)
    registered = MapView(image, pose, COLOUR, path, "kinect", 1000.0, DEPTH, transform)
    raw = MapView(image, pose, COLOUR, path, "as if registered")
    structure = build_from_depth([registered, raw], max_features=300, quiet=True)
    keypoints = structure.features[0].keypoints
    truth = surface_points(world, pose, COLOUR, keypoints)
    errors = np.linalg.norm(structure.points[0] - truth, axis=1)
    found = np.isfinite(errors)
    assert found.sum() > 100 and np.median(errors[found]) < 0.005
    unregistered = np.linalg.norm(structure.points[1] - truth, axis=1)
    assert np.nanmedian(unregistered) > 5 * np.median(errors[found])


def test_identity_registration_leaves_a_depth_map_as_it_was(kinect_view):
    _, _, _, raw, _ = kinect_view
    same = register_depth(raw, DEPTH, DEPTH, None)
    assert np.array_equal(np.isfinite(same), np.isfinite(raw))
    np.testing.assert_allclose(same[np.isfinite(raw)], raw[np.isfinite(raw)], rtol=1e-6)


def test_the_nearest_reading_wins_a_pixel():
    # Three readings of a depth sensor with a long focal length land within half a
    # pixel of the centre of a short-focal colour camera: it keeps the nearest.
    depth_camera = PinholeCamera(40.0, 40.0, 1.0, 0.0, 3, 1)
    colour_camera = PinholeCamera(1.0, 1.0, 1.0, 0.0, 3, 1)
    registered = register_depth(np.array([[3.0, 2.0, 1.0]]), depth_camera, colour_camera)
    assert registered[0, 1] == pytest.approx(1.0)
    assert np.isnan(registered[0, [0, 2]]).all()


@pytest.mark.parametrize(
    ("matrix", "words"),
    [
        (np.diag([1.0, 1.0, 2.0, 1.0]), "not a rotation"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "det R"),
        (np.vstack([np.eye(4)[:3], [0.0, 0.0, 0.1, 1.0]]), "last row"),
        (np.full((4, 4), np.nan), "NaN"),
        (np.eye(3), "4x4"),
    ],
)
def test_a_transform_that_is_not_rigid_is_one_error_naming_it(kinect_view, matrix, words):
    _, _, _, raw, path = kinect_view
    with pytest.raises(DataError, match=words):
        register_depth(raw, DEPTH, COLOUR, matrix)
    image = np.zeros((COLOUR.height, COLOUR.width, 3), np.uint8)
    with pytest.raises(DataError, match=f"map view 'v': depth_to_colour.*{words}"):
        MapView(image, Pose(np.zeros(3), [1.0, 0, 0, 0]), COLOUR, path, "v", 1000.0, DEPTH, matrix)


def test_a_bad_depth_camera_is_one_error(kinect_view):
    _, pose, _, raw, path = kinect_view
    with pytest.raises(DataError, match="depth camera is 640x480"):
        register_depth(raw, SEVENSCENES_DEPTH, COLOUR, None)
    with pytest.raises(DataError, match="depth_camera must be a PinholeCamera"):
        register_depth(raw, (292.5, 292.5, 159.5, 119.5), COLOUR, None)
    image = np.zeros((COLOUR.height, COLOUR.width, 3), np.uint8)
    with pytest.raises(DataError, match="depth_camera must be a PinholeCamera"):
        MapView(image, pose, COLOUR, path, "v", 1000.0, "585")
    wrong_size = MapView(image, pose, COLOUR, path, "v", 1000.0, SEVENSCENES_DEPTH)
    with pytest.raises(
        DataError, match="frame.depth.png: depth map is 320x240 but the depth camera"
    ):
        build_from_depth([wrong_size], quiet=True)


def test_the_cache_key_follows_the_depth_sensor(kinect_view):
    _, pose, transform, _, _ = kinect_view
    plain = structure_key(["a"], [pose], [COLOUR], {})
    assert structure_key(["a"], [pose], [COLOUR], {}, [(None, None)]) == plain
    with_sensor = structure_key(["a"], [pose], [COLOUR], {}, [(DEPTH, transform)])
    assert with_sensor != plain
    moved = transform.copy()
    moved[0, 3] += 0.001
    assert structure_key(["a"], [pose], [COLOUR], {}, [(DEPTH, moved)]) != with_sensor
    other_lens = PinholeCamera(290.0, 290.0, 159.5, 119.5, 320, 240)
    assert structure_key(["a"], [pose], [COLOUR], {}, [(other_lens, transform)]) != with_sensor


def test_the_kinect_calibration_is_rigid_and_about_2_5_cm_along_x():
    assert checked_rigid(SEVENSCENES_DEPTH_TO_COLOUR, "test") is not None
    translation = SEVENSCENES_DEPTH_TO_COLOUR[:3, 3]
    assert -0.03 < translation[0] < -0.02 and np.abs(translation[1:]).max() < 0.005
    assert not SEVENSCENES_DEPTH_TO_COLOUR.flags.writeable


def test_intrinsics_for_names_the_sensor_the_file_describes(raw_kinect_scene):
    from_file = load_sevenscenes(raw_kinect_scene, None, "test")[0].depth_camera
    depth_side = load_sevenscenes(raw_kinect_scene, None, "test", intrinsics_for="depth")[0]
    colour_side = load_sevenscenes(raw_kinect_scene, None, "test", intrinsics_for="colour")[0]
    size = (from_file.width, from_file.height)
    assert depth_side.depth_camera == from_file
    assert depth_side.camera == SEVENSCENES_COLOUR.scaled_to(*size)
    assert colour_side.camera == from_file
    assert colour_side.depth_camera == SEVENSCENES_DEPTH.scaled_to(*size)
    for frame in (depth_side, colour_side):
        assert frame.depth_to_colour is SEVENSCENES_DEPTH_TO_COLOUR


def test_an_unknown_sensor_is_a_config_error_naming_the_key(raw_kinect_scene):
    with pytest.raises(ConfigError, match="dataset.intrinsics_for must be one of depth, colour"):
        SevenScenes(str(raw_kinect_scene), None, intrinsics_for="rgb")
    with pytest.raises(ConfigError, match="dataset.intrinsics_for"):
        load_sevenscenes(raw_kinect_scene, None, "test", intrinsics_for="both")


def test_real_7scenes_frames_get_the_colour_and_depth_cameras(stairs_sample):
    frames = SevenScenes(str(stairs_sample), "stairs").frames("test")
    assert {(f.camera, f.depth_camera) for f in frames} == {(SEVENSCENES_COLOUR, SEVENSCENES_DEPTH)}


def test_intrinsics_for_leaves_the_trained_models_key_alone():
    # The network never sees a camera: a checkpoint trained under either sensor's
    # reading of camera-intrinsics.txt is the same model.
    from omegaconf import OmegaConf

    from relocfw.app.methods import dataset_settings

    def settings(sensor: str) -> dict:
        dataset = {"_target_": "relocfw.data.sevenscenes.SevenScenes", "root": "r"}
        return dataset_settings(
            OmegaConf.create({"dataset": {**dataset, "intrinsics_for": sensor}})
        )

    assert settings("depth") == settings("colour")
    assert "intrinsics_for" not in settings("depth") and settings("depth")["root"] == "r"


def test_colmap_points_leave_the_trained_models_key_alone():
    # dataset.points only decides whether the structure stage gets the model's 3-D
    # points: the images and poses the network trains on are the same.
    from omegaconf import OmegaConf

    from relocfw.app.methods import dataset_settings

    def settings(points: bool) -> dict:
        dataset = {"_target_": "relocfw.data.colmap.ColmapDataset", "root": "r"}
        return dataset_settings(OmegaConf.create({"dataset": {**dataset, "points": points}}))

    assert settings(True) == settings(False)
    assert "points" not in settings(True) and settings(True)["root"] == "r"
