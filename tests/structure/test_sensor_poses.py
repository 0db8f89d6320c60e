"""Poses of another sensor than the colour camera (relocfw.core.sensor_poses): with
dataset.poses_of=depth (7-Scenes' poses taken as its depth sensor's) the structure
refiners build and solve in the colour camera's poses and answer the depth sensor's.

The world is tests.structure.textured_world seen by a Kinect-like rig (the depth sensor
2.5 cm along x of the colour camera, turned by 1 degree, with a longer focal length);
the dataset's poses are the depth sensor's, as KinectFusion's are.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import orientation_error_deg, quaternion_to_matrix
from relocfw.core.refinement import MapImage, RefineQuery
from relocfw.core.sensor_poses import (
    STATE_KEY,
    colour_pose,
    map_pose_to_colour,
    reference_pose,
    stored_pose_to_colour,
)
from relocfw.core.values import Pose
from relocfw.data.sevenscenes import SEVENSCENES_DEPTH_TO_COLOUR, SevenScenes, load_sevenscenes
from relocfw.plugins.features_refiner import FeaturesRefiner
from relocfw.plugins.relative_refiner import RelativeRefiner
from tests.structure.test_registered_depth import (
    COLOUR,
    DEPTH,
    depth_sensor_pose,
    depth_to_colour,
)
from tests.structure.textured_world import (
    depth_map,
    looking_at,
    make_world,
    render,
    write_depth_png,
)

COLOUR_POSES = [
    looking_at([-0.3, 0.0, 0.0], [0.0, 0.0, 3.0]),
    looking_at([0.3, 0.05, 0.0], [0.0, 0.0, 3.0]),
]
QUERY_COLOUR_POSE = looking_at([0.05, 0.1, 0.2], [-0.1, 0.0, 3.0])


def test_the_colour_pose_is_the_sensor_pose_moved_by_the_rig_and_back():
    transform = depth_to_colour()
    sensor = looking_at([0.2, -0.1, 0.4], [1.0, 0.5, 3.0])
    colour = colour_pose(sensor, transform)
    # The colour camera's centre is the rig's colour centre, seen from the sensor.
    centre_in_sensor = np.linalg.inv(transform)[:3, 3]
    expected = sensor.position + quaternion_to_matrix(sensor.quaternion) @ centre_in_sensor
    np.testing.assert_allclose(colour.position, expected, atol=1e-12)
    assert np.linalg.norm(colour.position - sensor.position) == pytest.approx(0.025, abs=1e-9)
    assert orientation_error_deg(colour.quaternion, sensor.quaternion) == pytest.approx(1.0)
    back = reference_pose(colour, transform)
    np.testing.assert_allclose(back.position, sensor.position, atol=1e-12)
    assert orientation_error_deg(back.quaternion, sensor.quaternion) < 1e-6


def test_no_transform_and_a_nan_pose_pass_through():
    pose = looking_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    assert colour_pose(pose, None) is pose and reference_pose(pose, None) is pose
    broken = Pose([np.nan, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    assert colour_pose(broken, depth_to_colour()) is broken


def test_a_map_of_two_rigs_is_one_error_naming_both_images():
    pose = looking_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    image = np.zeros((COLOUR.height, COLOUR.width, 3), np.uint8)
    first = MapImage("a", image, pose, COLOUR, pose_to_colour=depth_to_colour())
    second = MapImage("b", image, pose, COLOUR, pose_to_colour=depth_to_colour(-0.05))
    plain = MapImage("c", image, pose, COLOUR)
    np.testing.assert_array_equal(map_pose_to_colour([first, first], "x"), depth_to_colour())
    assert map_pose_to_colour([plain, plain], "x") is None
    for other in (second, plain):
        with pytest.raises(ConfigError, match=r"refine=features: map images a and \w"):
            map_pose_to_colour([first, other], "refine=features")


def test_a_stored_transform_that_is_not_rigid_is_one_data_error_naming_the_key():
    scaled = torch.eye(4, dtype=torch.float64) * 2.0
    scaled[3, 3] = 1.0
    with pytest.raises(DataError, match=f"model: {STATE_KEY}"):
        stored_pose_to_colour({STATE_KEY: scaled}, "model")
    with pytest.raises(DataError, match=f"model: {STATE_KEY} must be a float64 tensor"):
        stored_pose_to_colour({STATE_KEY: torch.eye(4)}, "model")
    assert stored_pose_to_colour({}, "model") is None


@pytest.fixture(scope="module")
def kinect_map(tmp_path_factory):
    """Two map images of the rig, posed by the depth sensor, with raw depth PNGs."""
    folder = tmp_path_factory.mktemp("kinect_map")
    world = make_world(seed=0)
    transform = depth_to_colour()
    images = []
    for number, colour in enumerate(COLOUR_POSES):
        sensor = depth_sensor_pose(colour, transform)
        depth = write_depth_png(depth_map(world, sensor, DEPTH), folder / f"{number}.depth.png")
        images.append(
            MapImage(
                f"view-{number}",
                render(world, colour, COLOUR),
                sensor,
                COLOUR,
                depth,
                depth_camera=DEPTH,
                depth_to_colour=transform,
                pose_to_colour=transform,
            )
        )
    return world, transform, images


def test_features_builds_in_colour_poses_and_answers_the_sensor_pose(kinect_map):
    world, transform, images = kinect_map
    refiner = FeaturesRefiner(keyframes="pose", count=2, max_features=600, quiet=True)
    refiner.fit(images, np.eye(2))
    for stored, image in zip(refiner.structure.poses, images, strict=True):
        np.testing.assert_allclose(stored.position, colour_pose(image.pose, transform).position)
    truth = depth_sensor_pose(QUERY_COLOUR_POSE, transform)
    network = Pose(truth.position + [0.2, 0.0, 0.0], truth.quaternion)
    query = RefineQuery(render(world, QUERY_COLOUR_POSE, COLOUR), network, np.zeros(2))
    refined = refiner.refine(query)
    assert not refined.fell_back
    # The colour camera is 2.5 cm from the sensor: an answer left in the colour
    # camera's pose would miss by that much.
    assert np.linalg.norm(refined.pose.position - truth.position) < 0.005
    assert orientation_error_deg(refined.pose.quaternion, truth.quaternion) < 0.3
    # A model file keeps the transform, and the loaded refiner answers the same.
    state = refiner.state()
    np.testing.assert_array_equal(state[STATE_KEY].numpy(), transform)
    loaded = FeaturesRefiner()
    loaded.load_state(state)
    again = loaded.refine(query)
    np.testing.assert_allclose(again.pose.position, refined.pose.position, atol=1e-9)


def test_relative_keeps_colour_poses_and_the_transform(kinect_map):
    _, transform, images = kinect_map
    refiner = RelativeRefiner(count=2, max_features=300, quiet=True)
    refiner.fit(images, np.eye(2))
    expected = [colour_pose(image.pose, transform).position for image in images]
    np.testing.assert_allclose([p.position for p in refiner.structure.poses], expected)
    loaded = RelativeRefiner()
    loaded.load_state(refiner.state())
    np.testing.assert_array_equal(loaded.pose_to_colour, transform)


def test_7scenes_poses_are_the_colour_cameras_unless_told(raw_kinect_scene, tiny_scene):
    assert load_sevenscenes(raw_kinect_scene, None, "test")[0].pose_to_colour is None
    depth_side = load_sevenscenes(raw_kinect_scene, None, "test", poses_of="depth")[0]
    assert depth_side.pose_to_colour is SEVENSCENES_DEPTH_TO_COLOUR
    # Registered depth has no depth-to-colour transform: its poses are the colour's.
    registered = load_sevenscenes(tiny_scene, None, "test", poses_of="depth")[0]
    assert registered.pose_to_colour is None
    with pytest.raises(ConfigError, match="dataset.poses_of must be one of depth, colour"):
        SevenScenes(str(raw_kinect_scene), None, poses_of="rgb")


def test_poses_of_leaves_the_trained_models_key_alone():
    # The network learns the dataset's poses whichever sensor they describe.
    from omegaconf import OmegaConf

    from relocfw.app.methods import dataset_settings

    def settings(sensor: str) -> dict:
        dataset = {"_target_": "relocfw.data.sevenscenes.SevenScenes", "root": "r"}
        return dataset_settings(OmegaConf.create({"dataset": {**dataset, "poses_of": sensor}}))

    assert settings("depth") == settings("colour")
