"""The RGB-only map's multi-view tracks (relocfw.structure.tracks, covisibility)."""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError
from relocfw.core.values import Pose
from relocfw.plugins.features_refiner import FeaturesRefiner
from relocfw.structure.covisibility import covisible_partners, scene_depths
from relocfw.structure.features import LocalFeatures
from relocfw.structure.map_view import MapView
from relocfw.structure.tracks import (
    TrackSettings,
    epipolar_distances,
    pair_matches,
    solve_tracks,
    track_views,
    tracks_of_matches,
)
from relocfw.structure.triangulated_structure import build_by_triangulation
from relocfw.structure.triangulation import triangulate, world_to_camera
from tests.structure.textured_world import looking_at, make_world, render

CAMERA = PinholeCamera(525.0, 525.0, 320.0, 240.0, 640, 480)
SMALL = PinholeCamera(262.5, 262.5, 160.0, 120.0, 320, 240)


def project(points: np.ndarray, pose: Pose, camera: PinholeCamera) -> np.ndarray:
    rotation, translation = world_to_camera(pose)
    return camera.project(points @ rotation.T + translation)


def ring_of_views(count: int, spacing: float) -> list[Pose]:
    """Cameras in a row along x at z = 0, all looking at one point 3 m ahead."""
    xs = (np.arange(count) - (count - 1) / 2) * spacing
    return [looking_at([float(x), 0.0, 0.0], [0.0, 0.0, 3.0]) for x in xs]


def observed(points: np.ndarray, poses: list[Pose], noise_px: float, seed: int = 0):
    """Each view's keypoints: row k is point k's projection plus Gaussian noise, and
    tracks (one per point) over all views."""
    rng = np.random.default_rng(seed)
    keypoints = [
        project(points, pose, CAMERA) + rng.normal(0.0, noise_px, (len(points), 2))
        for pose in poses
    ]
    tracks = [
        np.column_stack([np.arange(len(poses)), np.full(len(poses), k)]) for k in range(len(points))
    ]
    return keypoints, tracks


def scene_points(count: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [rng.uniform(-0.6, 0.6, count), rng.uniform(-0.4, 0.4, count), rng.uniform(2.5, 3.5, count)]
    )


def test_a_track_of_n_views_triangulates_from_all_n_and_beats_two_views():
    poses = ring_of_views(6, 0.08)
    points = scene_points(200)
    keypoints, tracks = observed(points, poses, noise_px=0.7)
    views = track_views(tracks, keypoints, poses, [CAMERA] * 6)
    solved, used = solve_tracks(views, TrackSettings())
    assert used.all()  # every view of every track kept: no noise reaches 4 px
    n_view_error = np.linalg.norm(solved - points, axis=1)
    # Two-view points from the same observations: the neighbouring pair (what the
    # earlier nearest-first rule paired) and even the widest pair are worse.
    for other, margin in ((1, 0.3), (5, 0.9)):
        pair, valid = triangulate(
            keypoints[0], keypoints[other], CAMERA, poses[0], CAMERA, poses[other], 50.0, 0.0
        )
        assert valid.all()
        two_view_error = np.linalg.norm(pair - points, axis=1)
        assert np.median(n_view_error) < margin * np.median(two_view_error)
    assert np.median(n_view_error) < 0.05  # metres, at 3 m with 0.7 px noise


def test_an_outlier_view_is_dropped_and_the_track_re_solved():
    poses = ring_of_views(5, 0.1)
    points = scene_points(30)
    keypoints, tracks = observed(points, poses, noise_px=0.3)
    keypoints[2] = keypoints[2].copy()
    keypoints[2][:10] += [25.0, -15.0]  # a wrong match in view 2 for points 0-9
    views = track_views(tracks, keypoints, poses, [CAMERA] * 5)
    solved, used = solve_tracks(views, TrackSettings())
    assert not used[:10, 2].any() and used[:10].sum(axis=1).tolist() == [4] * 10
    assert used[10:].all()
    assert np.linalg.norm(solved - points, axis=1).max() < 0.05


def test_a_track_behind_a_camera_or_too_narrow_is_rejected():
    poses = ring_of_views(3, 0.1)
    points = scene_points(4)
    keypoints, tracks = observed(points, poses, noise_px=0.0)
    views = track_views(tracks, keypoints, poses, [CAMERA] * 3)
    # Ray angles at 3 m from 0.2 m apart are about 4 degrees.
    assert np.isfinite(solve_tracks(views, TrackSettings(min_angle_deg=2.0))[0]).all()
    narrow, used = solve_tracks(views, TrackSettings(min_angle_deg=10.0))
    assert np.isnan(narrow).all() and not used.any()


def test_an_image_holding_two_keypoints_of_a_track_leaves_it():
    # Image 1's keypoints 0 and 1 both join image 0's keypoint 0: inconsistent.
    matches = [
        (0, 1, np.array([[0, 0]])),
        (0, 2, np.array([[0, 0], [1, 1]])),
        (1, 2, np.array([[1, 0], [2, 1]])),
    ]
    tracks = tracks_of_matches([3, 3, 3], matches)
    as_sets = sorted(sorted(map(tuple, t.tolist())) for t in tracks)
    assert as_sets == [[(0, 0), (2, 0)], [(0, 1), (1, 2), (2, 1)]]


def test_the_epipolar_filter_rejects_a_wrong_match():
    poses = ring_of_views(2, 0.2)
    points = scene_points(40)
    keypoints = [project(points, pose, CAMERA) for pose in poses]
    right = epipolar_distances(keypoints[0], keypoints[1], CAMERA, poses[0], CAMERA, poses[1])
    assert right.max() < 1e-6
    rng = np.random.default_rng(3)
    descriptors = rng.random((40, 128)).astype(np.float32)
    moved = keypoints[1].copy()
    moved[7] += [0.0, 12.0]  # point 7's match in image 1 is another point
    features = [LocalFeatures(keypoints[0], descriptors), LocalFeatures(moved, descriptors)]
    found = pair_matches(features, poses, [CAMERA] * 2, [[1], [0]], TrackSettings(epipolar_px=2.0))
    assert len(found) == 1
    i, j, kept = found[0]
    assert (i, j) == (0, 1) and len(kept) == 39 and 7 not in kept[:, 0]


def test_partners_are_chosen_by_ray_angle_not_nearness():
    poses = ring_of_views(12, 0.03)
    depths = scene_depths(poses)
    np.testing.assert_allclose(depths, 3.0, rtol=0.02)  # the axes meet 3 m ahead
    chosen = covisible_partners(poses, [CAMERA] * 12, depths, 4, 1.5, 20.0)
    for i, partners in enumerate(chosen):
        assert len(partners) == 4
        # 1.5 degrees at 3 m is about 8 cm: the neighbours 3 and 6 cm away are not taken.
        assert all(abs(j - i) >= 3 for j in partners)


@pytest.mark.parametrize(
    ("values", "key"),
    [
        ({"partners": 0}, "refine.triangulation.partners"),
        ({"epipolar_px": -1.0}, "refine.triangulation.epipolar_px"),
        ({"min_views": 1}, "refine.triangulation.min_views"),
        ({"max_partner_angle_deg": 1.0}, "refine.triangulation.max_partner_angle_deg"),
        ({"min_angle_deg": "wide"}, "refine.triangulation.min_angle_deg"),
        ({"partner": 3}, "refine.triangulation.partner"),
        ({"method": "colmap"}, "refine.triangulation.method"),
    ],
)
def test_bad_settings_name_the_key_before_any_work(values, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        FeaturesRefiner(structure="triangulated", triangulation=values)


def test_tracks_give_far_more_points_than_two_view_medians():
    # Ten small images 3 cm apart looking at a room corner 2.2-3.2 m away: the
    # nearest partner at least 5 cm away is 6 cm off, whose rays meet at under 2
    # degrees beyond 1.7 m, so the two-view rule keeps little; tracks pick wider
    # partners and use every view.
    world = make_world(seed=0)
    poses = ring_of_views(10, 0.03)
    views = [
        MapView(render(world, pose, SMALL, supersample=1), pose, SMALL, None, f"v{n}")
        for n, pose in enumerate(poses)
    ]
    tracks = build_by_triangulation(views, max_features=400, quiet=True)
    two_view = build_by_triangulation(views, max_features=400, method="two_view", quiet=True)
    with_tracks = int(tracks.point_counts().sum())
    with_pairs = int(two_view.point_counts().sum())
    assert with_tracks >= 2 * with_pairs + 50
    # The track points are where the world is: on a surface 2.2-3.2 m deep.
    found = np.concatenate(tracks.points)
    found = found[np.isfinite(found).all(axis=1)]
    assert np.median(np.abs(found[:, 2] - np.clip(found[:, 2], 2.2, 3.2))) < 0.05
