"""One query against the map's structure, and the choice of keyframes by pose."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import orientation_error_deg
from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.features import extract_rootsift
from relocfw.structure.query_solver import StructureAnswer, keyframes_by_pose, localize_against
from tests.structure.textured_world import looking_at, make_texture


def test_a_query_between_two_views_is_localized_to_millimetres(synthetic_scene, depth_structure):
    answer = localize_against(
        depth_structure, synthetic_scene.query_image, synthetic_scene.camera, [0, 1]
    )
    assert isinstance(answer, StructureAnswer)
    assert answer.success
    truth = synthetic_scene.query_pose
    assert np.linalg.norm(answer.pose.position - truth.position) < 0.01
    assert orientation_error_deg(answer.pose.quaternion, truth.quaternion) < 0.5
    assert answer.inliers >= 200
    assert answer.correspondences >= answer.inliers
    assert set(answer.seconds) == {"features", "matching", "solve"}
    assert all(s >= 0 for s in answer.seconds.values())
    assert answer.total_seconds == pytest.approx(sum(answer.seconds.values()))


def test_precomputed_query_features_give_the_same_answer(synthetic_scene, depth_structure):
    camera = synthetic_scene.camera
    features = extract_rootsift(synthetic_scene.query_image, 1024)
    extracted = localize_against(depth_structure, synthetic_scene.query_image, camera, [0, 1])
    given = localize_against(depth_structure, None, camera, [0, 1], query_features=features)
    assert given.seconds["features"] < 0.01  # nothing extracted
    assert (given.inliers, given.correspondences) == (extracted.inliers, extracted.correspondences)
    assert np.array_equal(given.pose.position, extracted.pose.position)


def test_a_blank_query_has_no_correspondence_and_fails(synthetic_scene, depth_structure):
    blank = np.full_like(synthetic_scene.query_image, 128)
    answer = localize_against(depth_structure, blank, synthetic_scene.camera, [0, 1])
    assert (answer.success, answer.pose, answer.correspondences, answer.inliers) == (
        False,
        None,
        0,
        0,
    )


def test_an_unrelated_query_fails(synthetic_scene, depth_structure):
    elsewhere = make_texture(np.random.default_rng(99), 2.5, 1.875)  # 640 x 480 texels
    assert elsewhere.shape == (480, 640, 3)
    answer = localize_against(depth_structure, elsewhere, synthetic_scene.camera, [0, 1])
    assert not answer.success
    assert answer.pose is None
    assert answer.inliers < 12  # a few chance matches, no consistent pose


def test_no_keyframes_or_no_points_give_no_correspondence(synthetic_scene, depth_structure):
    camera = synthetic_scene.camera
    answer = localize_against(depth_structure, synthetic_scene.query_image, camera, [])
    assert (answer.success, answer.correspondences) == (False, 0)
    no_depth = build_from_depth(
        [dataclasses.replace(synthetic_scene.views[0], depth_path=None)], 200, quiet=True
    )
    answer = localize_against(no_depth, synthetic_scene.query_image, camera, [0])
    assert (answer.success, answer.correspondences) == (False, 0)


def test_repeated_keyframes_count_once(synthetic_scene, depth_structure):
    camera = synthetic_scene.camera
    once = localize_against(depth_structure, synthetic_scene.query_image, camera, [0, 1])
    twice = localize_against(depth_structure, synthetic_scene.query_image, camera, [0, 1, 0, 1])
    assert twice.correspondences == once.correspondences


def test_wrong_arguments_are_named(synthetic_scene, depth_structure):
    image, camera = synthetic_scene.query_image, synthetic_scene.camera
    with pytest.raises(DataError, match=r"keyframes\[1\] = 2"):
        localize_against(depth_structure, image, camera, [0, 2])
    with pytest.raises(DataError, match=r"keyframes\[0\] must be an integer"):
        localize_against(depth_structure, image, camera, [0.5])
    with pytest.raises(DataError, match="320x240 but the camera is 640x480"):
        localize_against(depth_structure, image[::2, ::2].copy(), camera, [0])
    with pytest.raises(DataError, match="both are None"):
        localize_against(depth_structure, None, camera, [0])
    with pytest.raises(DataError, match="query_image has dtype float"):
        localize_against(depth_structure, image / 255.0, camera, [0])
    with pytest.raises(ConfigError, match="ratio"):
        localize_against(depth_structure, image, camera, [0], ratio=1.5)
    with pytest.raises(ConfigError, match="max_error_px"):
        localize_against(depth_structure, image, camera, [0], max_error_px=0)
    with pytest.raises(ConfigError, match="min_inliers"):
        localize_against(depth_structure, image, camera, [0], min_inliers=3)


def test_keyframes_by_pose_are_the_nearest_looking_the_same_way():
    forward = [0.0, 0.0, 10.0]
    poses = [
        looking_at([0.0, 0.0, 0.0], forward),
        looking_at([1.0, 0.0, 0.0], forward),
        looking_at([0.08, 0.0, 0.0], [0.0, 0.0, -10.0]),  # nearest, but looks back
        looking_at([0.5, 0.0, 0.0], [10.0, 0.0, 10.0]),  # 45 degrees off: counts
        looking_at([0.4, 0.0, 0.0], [10.0, 0.0, 5.0]),  # 63 degrees off
    ]
    query = looking_at([0.05, 0.0, 0.0], forward)
    assert keyframes_by_pose(poses, query, 2) == [0, 3]
    assert keyframes_by_pose(poses, query, 10) == [0, 3, 1]  # only those within 45 deg
    assert keyframes_by_pose(poses, query, 10, max_angle_deg=90) == [0, 4, 3, 1]
    assert keyframes_by_pose(poses, query, 1, max_angle_deg=180) == [2]
    # Nothing looks its way: the nearest in position.
    up = looking_at([0.05, 0.0, 0.0], [0.0, -10.0, 0.01])
    assert keyframes_by_pose(poses, up, 2, max_angle_deg=10) == [2, 0]
    assert keyframes_by_pose([], query, 3) == []
    with pytest.raises(ConfigError, match="count"):
        keyframes_by_pose(poses, query, 0)
    with pytest.raises(ConfigError, match="max_angle_deg"):
        keyframes_by_pose(poses, query, 1, max_angle_deg=200)


def test_keyframes_by_pose_take_a_map(synthetic_scene, depth_structure):
    chosen = keyframes_by_pose(depth_structure, synthetic_scene.query_pose, 1)
    distances = [np.linalg.norm(p.position - synthetic_scene.query_pose.position)
                 for p in depth_structure.poses]  # fmt: skip
    assert chosen == [int(np.argmin(distances))]
