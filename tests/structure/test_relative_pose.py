"""The keyframe family's geometry: relative poses by the essential matrix, world rays,
their intersection, and the degenerate sets that must give no position (flagged by
the caller), never an exception."""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.core.geometry import orientation_error_deg, quaternion_to_matrix
from relocfw.core.values import Pose
from relocfw.structure.relative_pose import (
    QueryRay,
    intersect_rays,
    locate_by_rays,
    mean_rotation,
    query_ray,
    solve_relative_pose,
)
from tests.structure.scenes import points_in_view, to_camera
from tests.structure.textured_world import looking_at

pytest.importorskip("poselib")

CAMERA = PinholeCamera(525.0, 525.0, 320.0, 240.0, 640, 480)
QUERY_POSE = looking_at([0.1, -0.05, 0.3], [0.0, 0.1, 3.0])
KEYFRAME_POSES = [
    looking_at([-0.4, 0.0, 0.0], [0.1, 0.0, 3.0]),
    looking_at([0.5, 0.1, 0.05], [-0.1, 0.0, 3.0]),
    looking_at([0.0, -0.4, -0.2], [0.0, 0.2, 3.0]),
]


def project(pose: Pose, world: np.ndarray) -> np.ndarray:
    in_camera = to_camera(pose, world)
    return np.column_stack(
        [
            CAMERA.fx * in_camera[:, 0] / in_camera[:, 2] + CAMERA.cx,
            CAMERA.fy * in_camera[:, 1] / in_camera[:, 2] + CAMERA.cy,
        ]
    )


def pair(
    keyframe: Pose,
    seed: int = 0,
    noise_px: float = 0.0,
    outliers: float = 0.0,
    query: Pose = QUERY_POSE,
    count: int = 150,
) -> tuple[np.ndarray, np.ndarray]:
    """Matched pixels (keyframe, query) of points the query sees at 1.5-4 m; a share
    of the query's replaced by random pixels (wrong matches)."""
    rng = np.random.default_rng(seed)
    query_pixels, world = points_in_view(rng, CAMERA, query, count, near=1.5, far=4.0)
    keyframe_pixels = project(keyframe, world)
    keyframe_pixels = keyframe_pixels + rng.normal(0, noise_px, keyframe_pixels.shape)
    query_pixels = query_pixels + rng.normal(0, noise_px, query_pixels.shape)
    wrong = rng.random(count) < outliers
    query_pixels[wrong] = rng.uniform([0, 0], [639, 479], (int(wrong.sum()), 2))
    return keyframe_pixels, query_pixels


def ray_of(keyframe: Pose, **options) -> QueryRay:
    keyframe_pixels, query_pixels = pair(keyframe, **options)
    relative = solve_relative_pose(keyframe_pixels, query_pixels, CAMERA, CAMERA, 2.0, 15)
    assert relative.success
    return query_ray(keyframe, relative)


def angle_to_truth(ray: QueryRay, centre: np.ndarray) -> float:
    towards = (centre - ray.origin) / np.linalg.norm(centre - ray.origin)
    return float(np.degrees(np.arccos(np.clip(ray.direction @ towards, -1, 1))))


def test_a_noise_free_pair_gives_the_true_rotation_and_direction():
    keyframe = KEYFRAME_POSES[0]
    keyframe_pixels, query_pixels = pair(keyframe)
    relative = solve_relative_pose(keyframe_pixels, query_pixels, CAMERA, CAMERA, 1.0, 15)
    assert relative.success and relative.inliers == 150
    assert relative.parallax_deg > 3.0  # 0.5 m apart at 1.5-4 m: several degrees
    ray = query_ray(keyframe, relative)
    truth = quaternion_to_matrix(QUERY_POSE.quaternion)
    assert np.abs(ray.rotation - truth).max() < 1e-6
    assert angle_to_truth(ray, QUERY_POSE.position) < 1e-4
    assert ray.weight == 150.0


def test_noise_and_wrong_matches_keep_rotation_and_direction_close():
    for number, keyframe in enumerate(KEYFRAME_POSES):
        ray = ray_of(keyframe, seed=number, noise_px=0.7, outliers=0.3)
        truth = quaternion_to_matrix(QUERY_POSE.quaternion)
        cosine = (np.trace(ray.rotation.T @ truth) - 1) / 2
        assert np.degrees(np.arccos(min(cosine, 1.0))) < 0.5
        assert angle_to_truth(ray, QUERY_POSE.position) < 3.0
        assert 90 <= ray.weight <= 115  # about the 70% true matches, not the random ones


def test_two_or_more_keyframes_place_the_query_where_its_rays_meet():
    rays = [ray_of(pose) for pose in KEYFRAME_POSES]
    for chosen in (rays[:2], rays):
        located = locate_by_rays(chosen, min_rays=2, min_angle_deg=3.0, max_error_deg=2.0)
        assert located.reason == "" and len(located.used) == len(chosen)
        assert np.linalg.norm(located.position - QUERY_POSE.position) < 1e-4
    assert orientation_error_deg(mean_rotation(rays), QUERY_POSE.quaternion) < 1e-4
    noisy = [ray_of(p, seed=n, noise_px=0.7, outliers=0.3) for n, p in enumerate(KEYFRAME_POSES)]
    located = locate_by_rays(noisy, min_rays=2, min_angle_deg=3.0, max_error_deg=5.0)
    assert np.linalg.norm(located.position - QUERY_POSE.position) < 0.05
    assert orientation_error_deg(mean_rotation(noisy), QUERY_POSE.quaternion) < 0.5


def test_a_wrong_keyframe_is_outvoted_not_averaged_in():
    rays = [ray_of(pose) for pose in KEYFRAME_POSES]
    wrong = QueryRay(np.array([0.3, 0.3, 0.0]), np.array([0.0, 0.0, 1.0]), np.eye(3), 100.0)
    located = locate_by_rays([*rays, wrong], 2, 3.0, 2.0)
    assert located.used == (0, 1, 2)
    assert np.linalg.norm(located.position - QUERY_POSE.position) < 1e-4


def test_intersect_rays_solves_least_squares_and_refuses_parallel_lines():
    point = np.array([0.2, -0.1, 1.5])
    origins = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, -1.0]])
    directions = point - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    assert np.allclose(intersect_rays(origins, directions), point, atol=1e-12)
    assert np.allclose(intersect_rays(origins, directions, np.array([1.0, 5.0, 2.0])), point)
    parallel = np.tile([0.0, 0.0, 1.0], (3, 1))
    assert intersect_rays(origins, parallel) is None
    assert intersect_rays(origins[:1], directions[:1]) is None


def synthetic_ray(origin: list[float], towards: list[float], weight: float = 50.0) -> QueryRay:
    direction = np.subtract(towards, origin, dtype=float)
    return QueryRay(
        np.array(origin, float), direction / np.linalg.norm(direction), np.eye(3), weight
    )


@pytest.mark.parametrize(
    "rays, reason",
    [
        ([], "0 usable keyframes, fewer than 2"),
        ([synthetic_ray([0, 0, 0], [0, 0, 1])], "1 usable keyframes, fewer than 2"),
        # Collinear: both keyframes on the line through the query; their rays coincide.
        (
            [synthetic_ray([0, 0, 0], [0, 0, 1]), synthetic_ray([0, 0, 0.5], [0, 0, 1])],
            "no two rays cross",
        ),
        # Parallel rays from keyframes side by side: they meet nowhere.
        (
            [synthetic_ray([0, 0, 0], [0, 0, 1]), synthetic_ray([0.5, 0, 0], [0.5, 0, 1])],
            "no two rays cross",
        ),
        # One place, two directions: no baseline, the crossing is the keyframe itself.
        (
            [synthetic_ray([0, 0, 0], [0, 0, 1]), synthetic_ray([0, 0, 0], [1, 0, 1])],
            "no two rays cross",
        ),
        # Keyframes 1 mm apart for a query 2 m away: they subtend 0.03 degrees.
        (
            [synthetic_ray([0, 0, 0], [0, 0, 2]), synthetic_ray([0.001, 0, 0], [0, 0, 2])],
            "no two rays cross",
        ),
        # Rays that diverge: their nearest points lie behind one of them.
        (
            [synthetic_ray([0, 0, 0], [-1, 0, 1]), synthetic_ray([1, 0, 0], [2, 0, 1])],
            "fewer than 2 rays agree",
        ),
    ],
)
def test_degenerate_ray_sets_give_no_position_and_say_why(rays, reason):
    located = locate_by_rays(rays, min_rays=2, min_angle_deg=3.0, max_error_deg=5.0)
    assert located.position is None
    assert located.reason.startswith(reason)


def test_too_few_matches_or_no_motion_fail_without_raising():
    keyframe_pixels, query_pixels = pair(KEYFRAME_POSES[0], count=20)
    few = solve_relative_pose(keyframe_pixels[:4], query_pixels[:4], CAMERA, CAMERA)
    assert not few.success and few.inliers == 0
    none = solve_relative_pose(np.zeros((0, 2)), np.zeros((0, 2)), CAMERA, CAMERA)
    assert not none.success
    below = solve_relative_pose(keyframe_pixels, query_pixels, CAMERA, CAMERA, 2.0, 25)
    assert not below.success and below.inliers == 20  # found, but fewer than 25
    # The query turned on the spot: a rotation, but its matches show no parallax.
    turned = looking_at(QUERY_POSE.position.tolist(), [0.4, 0.0, 3.0])
    keyframe_pixels, query_pixels = pair(turned, noise_px=0.3)
    spun = solve_relative_pose(keyframe_pixels, query_pixels, CAMERA, CAMERA, 2.0, 15)
    assert spun.parallax_deg < 0.2


def test_bad_arrays_are_one_data_error_naming_them():
    with pytest.raises(DataError, match="keyframe_pixels has 3 rows, query_pixels 2"):
        solve_relative_pose(np.zeros((3, 2)), np.zeros((2, 2)), CAMERA, CAMERA)
    with pytest.raises(DataError, match="query_pixels has 1 rows with NaN"):
        solve_relative_pose(np.zeros((2, 2)), np.array([[0, 0], [np.nan, 1]]), CAMERA, CAMERA)
