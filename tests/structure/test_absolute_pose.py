"""PnP through PoseLib: a known pose from noisy correspondences with outliers."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from relocfw.core.camera import SEVENSCENES_DEFAULT
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import orientation_error_deg
from relocfw.structure.absolute_pose import solve_absolute_pose
from tests.structure.scenes import points_in_view, random_pose

pytest.importorskip("poselib")  # in the test extra (relocfw[structure]), so CI runs these

CAMERA = SEVENSCENES_DEFAULT


def noisy_problem(seed: int, count: int = 300, outliers: float = 0.3, noise_px: float = 1.0):
    """Correspondences of a random camera: Gaussian pixel noise, a share replaced by
    random pixels (wrong matches)."""
    rng = np.random.default_rng(seed)
    truth = random_pose(rng)
    pixels, world = points_in_view(rng, CAMERA, truth, count)
    pixels = pixels + rng.normal(0.0, noise_px, pixels.shape)
    wrong = rng.random(count) < outliers
    pixels[wrong] = rng.uniform([0, 0], [CAMERA.width, CAMERA.height], (int(wrong.sum()), 2))
    return truth, pixels, world, wrong


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_a_known_pose_from_noisy_matches_with_outliers(seed):
    truth, pixels, world, wrong = noisy_problem(seed)
    result = solve_absolute_pose(pixels, world, CAMERA, max_error_px=4.0)
    assert result.success and result.pose is not None
    assert np.linalg.norm(result.pose.position - truth.position) < 0.01  # < 1 cm
    assert orientation_error_deg(result.pose.quaternion, truth.quaternion) < 0.1
    # Every inlier but a few lucky outliers that land near their true pixel.
    assert (~wrong).sum() - 5 <= result.inliers <= (~wrong).sum() + 5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fewer_least_rounds_find_the_same_pose_when_inliers_abound(seed):
    # 70% inliers: the confidence rule stops after a few hundred rounds at most, so
    # a least number of 50 still finds the pose (and its refinement the same one).
    truth, pixels, world, _ = noisy_problem(seed)
    many = solve_absolute_pose(pixels, world, CAMERA, max_error_px=4.0)
    few = solve_absolute_pose(pixels, world, CAMERA, max_error_px=4.0, min_iterations=50)
    assert few.success and abs(few.inliers - many.inliers) <= 2
    assert np.linalg.norm(few.pose.position - many.pose.position) < 0.002
    assert np.linalg.norm(few.pose.position - truth.position) < 0.01


def test_the_least_rounds_reach_poselib(monkeypatch):
    import poselib

    seen = []
    real = poselib.estimate_absolute_pose

    def recording(points_2d, points_3d, camera, ransac, bundle):
        seen.append(dict(ransac))
        return real(points_2d, points_3d, camera, ransac, bundle)

    monkeypatch.setattr(poselib, "estimate_absolute_pose", recording)
    truth, pixels, world, _ = noisy_problem(4)
    solve_absolute_pose(pixels, world, CAMERA, min_iterations=50)
    solve_absolute_pose(pixels, world, CAMERA)
    assert [r["min_iterations"] for r in seen] == [50, 1000]
    with pytest.raises(ConfigError, match="at most 100000"):
        solve_absolute_pose(pixels, world, CAMERA, min_iterations=2**40)


def test_exact_correspondences_give_the_exact_pose():
    rng = np.random.default_rng(7)
    truth = random_pose(rng)
    pixels, world = points_in_view(rng, CAMERA, truth, 50)
    result = solve_absolute_pose(pixels, world, CAMERA)
    assert result.success and result.inliers == 50
    assert np.allclose(result.pose.position, truth.position, atol=1e-6)
    assert orientation_error_deg(result.pose.quaternion, truth.quaternion) < 1e-5


@pytest.mark.parametrize("count", [0, 1, 3])
def test_fewer_than_four_matches_fail_without_raising(count):
    truth, pixels, world, _ = noisy_problem(3, count=10, outliers=0.0)
    result = solve_absolute_pose(pixels[:count], world[:count], CAMERA)
    assert not result.success and result.pose is None and result.inliers == 0


def test_fewer_inliers_than_required_fail():
    truth, pixels, world, _ = noisy_problem(4, count=10, outliers=0.0, noise_px=0.0)
    result = solve_absolute_pose(pixels, world, CAMERA, min_inliers=12)
    assert not result.success and result.pose is None and result.inliers == 10


def test_pure_outliers_fail():
    rng = np.random.default_rng(5)
    pixels = rng.uniform([0, 0], [640, 480], (200, 2))
    world = rng.uniform(-2, 2, (200, 3))
    result = solve_absolute_pose(pixels, world, CAMERA, max_error_px=2.0, min_inliers=30)
    assert not result.success and result.pose is None


@pytest.mark.parametrize(
    "pixels, points, message",
    [
        (np.zeros((5, 3)), np.zeros((5, 3)), "points_2d must be an \\[N, 2\\]"),
        (np.zeros((5, 2)), np.zeros((5, 2)), "points_3d must be an \\[N, 3\\]"),
        (np.zeros((5, 2)), np.zeros((6, 3)), "points_2d has 5 rows, points_3d 6"),
        (np.full((5, 2), np.nan), np.zeros((5, 3)), "points_2d has 5 rows with NaN"),
    ],
)
def test_malformed_correspondences_raise_one_data_error(pixels, points, message):
    with pytest.raises(DataError, match=message):
        solve_absolute_pose(pixels, points, CAMERA)


@pytest.mark.parametrize(
    "options, name",
    [
        ({"max_error_px": 0.0}, "max_error_px"),
        ({"min_inliers": 3}, "min_inliers"),
        ({"min_iterations": 0}, "min_iterations"),
    ],
)
def test_impossible_options_raise_a_config_error_naming_them(options, name):
    truth, pixels, world, _ = noisy_problem(6, count=20)
    with pytest.raises(ConfigError, match=name):
        solve_absolute_pose(pixels, world, CAMERA, **options)


def test_missing_poselib_is_one_config_error_saying_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "poselib", None)  # makes `import poselib` fail
    truth, pixels, world, _ = noisy_problem(6, count=20)
    with pytest.raises(ConfigError, match=r'pip install "relocfw\[structure\]"'):
        solve_absolute_pose(pixels, world, CAMERA)
