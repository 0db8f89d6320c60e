import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from relocfw.core.errors import DataError
from relocfw.core.geometry import (
    matrix_to_quaternion,
    mean_quaternion,
    nearest_rotation,
    orientation_error_deg,
    pose_from_matrix,
    pose_to_matrix,
    position_error,
    quaternion_to_matrix,
)
from relocfw.core.values import Pose
from tests.rotations import axis_angle


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


def xyzw(q):
    return np.roll(np.asarray(q, dtype=np.float64), -1, axis=-1)


def test_conversions_are_scipys_with_w_first():
    for q in random_quaternions(50, seed=3):
        assert np.allclose(quaternion_to_matrix(q), Rotation.from_quat(xyzw(q)).as_matrix())
        assert np.allclose(quaternion_to_matrix(3 * q), quaternion_to_matrix(q))  # any norm
    # w first, then x, y, z: 90 degrees about z.
    assert np.allclose(
        matrix_to_quaternion(quaternion_to_matrix([1, 0, 0, 1])), [0.5**0.5, 0, 0, 0.5**0.5]
    )


def test_matrix_to_quaternion_is_on_one_hemisphere():
    for q in random_quaternions(50, seed=4):
        assert matrix_to_quaternion(quaternion_to_matrix(-q))[0] >= 0
    # 180 degrees about x: w = 0, the first non-zero component is positive.
    assert np.allclose(matrix_to_quaternion(np.diag([1.0, -1, -1])), [0, 1, 0, 0])


def test_a_drifted_matrix_gives_a_quaternion_near_its_nearest_rotation():
    # matrix_to_quaternion keeps the hand-written quaternion of the matrix as it is
    # (what every model so far was trained on), within ~1e-4 of its nearest rotation.
    rng = np.random.default_rng(5)
    rotation = Rotation.random(random_state=rng).as_matrix()
    drifted = rotation + 1e-4 * rng.normal(size=(3, 3))
    nearest = nearest_rotation(drifted)
    assert np.allclose(nearest.T @ nearest, np.eye(3), atol=1e-12)
    assert np.linalg.det(nearest) == pytest.approx(1.0)
    assert np.allclose(quaternion_to_matrix(matrix_to_quaternion(drifted)), nearest, atol=1e-3)
    assert (
        orientation_error_deg(matrix_to_quaternion(drifted), matrix_to_quaternion(rotation)) < 0.05
    )


def test_mean_quaternion_is_scipys_chordal_mean():
    q = random_quaternions(30, seed=6) * np.random.default_rng(6).uniform(0.5, 2, size=(30, 1))
    weights = np.random.default_rng(7).uniform(0.1, 3, size=30)
    for w in (None, weights):
        expected = np.roll(Rotation.from_quat(xyzw(q)).mean(w).as_quat(), 1)
        mean = mean_quaternion(q, w)
        assert mean[0] >= 0
        assert np.allclose(mean, expected if expected[0] >= 0 else -expected, atol=1e-12)


def test_mean_quaternion_over_batch_axes_is_each_items_mean():
    rng = np.random.default_rng(8)
    q = rng.normal(size=(3, 5, 20, 4))
    weights = rng.uniform(0.1, 3, size=(3, 5, 20))
    means = mean_quaternion(q, weights)
    assert means.shape == (3, 5, 4)
    for i in range(3):
        for j in range(5):
            assert np.allclose(means[i, j], mean_quaternion(q[i, j], weights[i, j]), atol=1e-12)
    assert np.all(means[..., 0] >= 0)


def test_a_mean_with_w_zero_follows_the_pose_hemisphere_rule():
    # 180 degrees about y, given with both signs: w = 0, so y decides (positive).
    q = np.array([[0.0, 0, -1, 0], [0.0, 0, 1, 0]])
    assert np.allclose(mean_quaternion(q), [0, 0, 1, 0])
    assert np.allclose(mean_quaternion(q), Pose(np.zeros(3), mean_quaternion(q)).quaternion)
