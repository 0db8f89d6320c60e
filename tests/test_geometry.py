import numpy as np
import pytest

from relocfw.core.errors import DataError
from relocfw.core.geometry import (
    matrix_to_quaternion,
    mean_quaternion,
    orientation_error_deg,
    pose_from_matrix,
    pose_to_matrix,
    position_error,
    quaternion_to_matrix,
)
from relocfw.core.values import Pose


def axis_angle(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    half = np.radians(degrees) / 2
    return np.array([np.cos(half), *(np.sin(half) * axis)])


def random_quaternions(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_quaternion_matrix_round_trip():
    for q in random_quaternions(200):
        back = matrix_to_quaternion(quaternion_to_matrix(q))
        assert np.allclose(back, q if q[0] >= 0 else -q, atol=1e-10)


def test_round_trip_near_180_degrees():
    # The trace formula loses precision here; the largest-component branch must not.
    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0.2]):
        q = axis_angle(axis, 179.999)
        back = matrix_to_quaternion(quaternion_to_matrix(q))
        assert orientation_error_deg(back, q) < 1e-6


def test_matrix_of_known_rotation():
    r = quaternion_to_matrix(axis_angle([0, 0, 1], 90))
    assert np.allclose(r @ [1, 0, 0], [0, 1, 0])


def test_pose_matrix_round_trip():
    pose = Pose([1.0, -2.0, 0.5], axis_angle([0.3, 1, -0.2], 37))
    back = pose_from_matrix(pose_to_matrix(pose))
    assert np.allclose(back.position, pose.position)
    assert np.allclose(back.quaternion, pose.quaternion)


def test_orientation_error_formula():
    a = axis_angle([0, 0, 1], 10)
    b = axis_angle([0, 0, 1], 40)
    assert orientation_error_deg(a, b) == pytest.approx(30.0)
    # q and -q are the same rotation.
    assert orientation_error_deg(b, -b) == pytest.approx(0.0, abs=1e-6)
    # 2 * acos(|<q1, q2>|) on unit quaternions, checked directly.
    q1, q2 = random_quaternions(2, seed=3)
    expected = np.degrees(2 * np.arccos(abs(np.dot(q1, q2))))
    assert orientation_error_deg(q1, q2) == pytest.approx(expected)
    # Un-normalised inputs are normalised first.
    assert orientation_error_deg(3 * a, b) == pytest.approx(30.0)


def test_position_error_is_euclidean():
    assert position_error([1, 2, 2], [0, 0, 0]) == pytest.approx(3.0)


@pytest.mark.parametrize(
    "matrix, message",
    [
        (np.diag([1.0, 2.0, 1.0, 1.0]), "not orthonormal"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
        (np.full((4, 4), np.nan), "NaN"),
        (np.eye(3), "4x4"),
        (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row"),
    ],
)
def test_non_rigid_poses_are_refused(matrix, message):
    with pytest.raises(DataError, match=message) as error:
        pose_from_matrix(matrix, source="frame.pose.txt")
    assert "frame.pose.txt" in str(error.value)


def test_mean_quaternion_ignores_sign_flips():
    base = axis_angle([0, 0, 1], 20)
    spread = [axis_angle([0, 0, 1], 20 + d) for d in (-5, 5)]
    flipped = np.stack([base, -spread[0], spread[1]])
    assert orientation_error_deg(mean_quaternion(flipped), base) < 1e-6
