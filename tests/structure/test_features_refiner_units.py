"""refine=features (plugins/features_refiner.py) on small synthetic worlds: which
keyframes it retrieves, when it falls back, the metres its depth maps are read in and
the confidence it answers.

Each test pins one behaviour a plausible slip would break: retrieving by the raw
rather than the standardised query descriptor, the farthest rather than the nearest
images, never saying it fell back, reading a TUM depth map (5000 units per metre) as
millimetres, a confidence that is not the solve's inlier count.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from relocfw import MapImage, Pose
from relocfw.core.camera import SEVENSCENES_DEFAULT
from relocfw.core.geometry import orientation_error_deg
from relocfw.core.refinement import RefineQuery
from relocfw.plugins.features_refiner import FeaturesRefiner
from relocfw.structure.query_solver import localize_against
from tests.structure.conftest import SyntheticScene
from tests.structure.textured_world import looking_at, make_world, render, write_depth_png

SMALL_CAMERA = SEVENSCENES_DEFAULT.scaled_to(160, 120)
# Five map images 0.5 m apart along x, all looking along +z at the room's back wall.
ALONG_X = [0.0, 0.5, 1.0, 1.5, 2.0]


@pytest.fixture(scope="module")
def small_map(tmp_path_factory: pytest.TempPathFactory) -> list[MapImage]:
    """Five small textured map images with a flat depth map each (for the keyframe
    tests only the map's poses and descriptors matter; the images give it keypoints)."""
    folder: Path = tmp_path_factory.mktemp("small_map")
    world = make_world(seed=1)
    depth = write_depth_png(np.full((120, 160), 2.5), folder / "flat.depth.png")
    views = []
    for number, x in enumerate(ALONG_X):
        pose = looking_at([x - 1.0, 0.0, 0.0], [x - 1.0, 0.0, 3.0])
        image = render(world, pose, SMALL_CAMERA, supersample=1)
        views.append(MapImage(f"frame-{number}", image, pose, SMALL_CAMERA, depth))
    return views


def fitted(views: list[MapImage], descriptors: np.ndarray, **options) -> FeaturesRefiner:
    refiner = FeaturesRefiner(max_features=256, quiet=True, **options)
    refiner.fit(views, np.asarray(descriptors, dtype=np.float64))
    return refiner


def query_of(descriptor: list[float], network_pose: Pose | None = None) -> RefineQuery:
    pose = network_pose or Pose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    blank = np.full((SMALL_CAMERA.height, SMALL_CAMERA.width, 3), 128, np.uint8)
    return RefineQuery(blank, pose, np.array(descriptor, dtype=np.float64))


def test_keyframes_by_descriptor_compare_the_standardised_query(small_map):
    # Dimension 0 spreads about a hundred times wider than dimension 1 over the map.
    # Raw, the query is nearest image 0 (29.07 against 31.0); standardised (each
    # dimension over its spread: 83.8 and 0.816, worked out by hand) the gap of 2 in
    # dimension 1 weighs 2.45, so it is nearest image 1 (0.37 against 2.47).
    descriptors = [[0.0, 0.0], [60.0, 2.0], [200.0, 1.0]]
    query = [29.0, 2.0]
    raw = np.linalg.norm(np.subtract(descriptors, query), axis=1)
    assert int(np.argmin(raw)) == 0  # the raw comparison would pick another image
    refiner = fitted(small_map[:3], descriptors, keyframes="descriptor", count=1)
    assert refiner.keyframes_of(query_of(query)) == [1]


def test_keyframes_by_descriptor_are_the_nearest_nearest_first(small_map):
    # One live dimension: standardised distances keep the raw order. From 2.8:
    # 3 (0.2), 1 (1.8), 0 (2.8), 6 (3.2), 10 (7.2).
    descriptors = [[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [6.0, 0.0], [10.0, 0.0]]
    refiner = fitted(small_map, descriptors, keyframes="descriptor", count=2)
    assert refiner.keyframes_of(query_of([2.8, 0.0])) == [2, 1]
    refiner = fitted(small_map, descriptors, keyframes="descriptor", count=4)
    assert refiner.keyframes_of(query_of([2.8, 0.0])) == [2, 1, 0, 3]


def test_keyframes_by_pose_are_the_nearest_nearest_first(small_map):
    descriptors = np.arange(10.0).reshape(5, 2)  # not used to choose here
    refiner = fitted(small_map, descriptors, keyframes="pose", count=2)
    # Map images at x = -1, -0.5, 0, 0.5, 1 m; the network says x = 0.35 m.
    network_pose = looking_at([0.35, 0.0, 0.0], [0.35, 0.0, 3.0])
    assert refiner.keyframes_of(query_of([0.0, 0.0], network_pose)) == [3, 2]


def map_images(scene: SyntheticScene, folder: Path, units_per_metre: float) -> list[MapImage]:
    """The scene's first two views (the query lies between them) as MapImages, their
    depth written `units_per_metre` units per metre (1000: 7-Scenes, 5000: TUM)."""
    images = []
    for number, (view, depth) in enumerate(zip(scene.views[:2], scene.depths[:2], strict=True)):
        path = write_depth_png(depth, folder / f"view-{number}.depth.png", units_per_metre)
        images.append(
            MapImage(view.name, view.image, view.pose, view.camera, path, units_per_metre)
        )
    return images


def network_guess(scene: SyntheticScene) -> Pose:
    """A network's pose 30 cm off the truth: a fallback is told apart from a solve."""
    truth = scene.query_pose
    return Pose(truth.position + [0.3, 0.0, 0.0], truth.quaternion)


@pytest.fixture(scope="module")
def tum_refiner(synthetic_scene, tmp_path_factory) -> FeaturesRefiner:
    """refine=features fitted on the scene's two views with TUM-scaled depth maps."""
    folder = tmp_path_factory.mktemp("tum_depth")
    refiner = FeaturesRefiner(keyframes="pose", count=2, quiet=True)
    refiner.fit(map_images(synthetic_scene, folder, 5000.0), np.eye(2))
    return refiner


def test_a_tum_depth_map_is_read_in_metres(synthetic_scene, tum_refiner):
    # Read as millimetres, every map point would lie 5 times too far from its camera
    # and no pose would fit the query's matches.
    scene = synthetic_scene
    query = RefineQuery(scene.query_image, network_guess(scene), np.zeros(2))
    refined = tum_refiner.refine(query)
    assert not refined.fell_back
    assert np.linalg.norm(refined.pose.position - scene.query_pose.position) < 0.01
    assert orientation_error_deg(refined.pose.quaternion, scene.query_pose.quaternion) < 0.5


def test_a_query_that_cannot_be_solved_falls_back_to_the_network_pose(synthetic_scene, tum_refiner):
    scene = synthetic_scene
    guess = network_guess(scene)
    blank = np.full_like(scene.query_image, 128)  # no texture: no keypoint, no match
    refined = tum_refiner.refine(RefineQuery(blank, guess, np.zeros(2)))
    assert refined.fell_back
    np.testing.assert_array_equal(refined.pose.position, guess.position)
    np.testing.assert_array_equal(refined.pose.quaternion, guess.quaternion)
    assert refined.confidence == 0.0  # no inlier


def test_the_confidence_is_the_solves_inlier_count(synthetic_scene, tum_refiner):
    scene = synthetic_scene
    whole = scene.query_image
    # The same query with its right two thirds blanked: fewer matches, still solved.
    part = whole.copy()
    part[:, whole.shape[1] // 3 :] = 128
    confidences = []
    for image in (whole, part):
        refined = tum_refiner.refine(RefineQuery(image, network_guess(scene), np.zeros(2)))
        solved = localize_against(tum_refiner.structure, image, scene.camera, [0, 1])
        assert not refined.fell_back and solved.success
        assert refined.confidence == float(solved.inliers)
        confidences.append(refined.confidence)
    assert confidences[0] > confidences[1] >= 12  # more inliers, more confidence
