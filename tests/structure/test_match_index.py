"""The map's descriptors stacked once (MatchIndex) and SIFT on a smaller image."""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import orientation_error_deg
from relocfw.structure import match_index as match_index_module
from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.features import extract_rootsift, to_full_image
from relocfw.structure.match_index import KnownMatches, MatchIndex
from relocfw.structure.query_solver import correspondences_of, localize_against
from tests.structure.test_features import textured_image


def test_every_keypoint_index_gives_the_bare_maps_correspondences(
    synthetic_scene, triangulated_structure
):
    # A triangulated map: many keypoints without a point, so the two paths could differ.
    query = extract_rootsift(synthetic_scene.query_image, 1024)
    index = MatchIndex.of(triangulated_structure, points_only=False)
    for keyframes in ([0, 1], [2, 0, 1], [1]):
        bare = correspondences_of(triangulated_structure, query, keyframes, 0.8)
        stacked = index.correspondences(query, keyframes, 0.8)
        assert len(bare[0]) > 20
        np.testing.assert_array_equal(stacked[0], bare[0])
        np.testing.assert_array_equal(stacked[1], bare[1])


def test_known_matches_are_not_matched_again_and_answer_the_same(
    synthetic_scene, triangulated_structure, monkeypatch
):
    # A second keyframe set that shares keyframes with the first matches only the
    # others, and gives what matching it from scratch gives.
    query = extract_rootsift(synthetic_scene.query_image, 1024)
    index = MatchIndex.of(triangulated_structure, points_only=False)
    fresh = [index.correspondences(query, k, 0.8) for k in ([0, 1], [2, 1, 0], [1])]
    matched = []
    real = match_index_module.matches_of_distances

    def counted(distances, ratio):
        matched.append(distances.shape[1])
        return real(distances, ratio)

    monkeypatch.setattr(match_index_module, "matches_of_distances", counted)
    known = KnownMatches()
    again = [index.correspondences(query, k, 0.8, known) for k in ([0, 1], [2, 1, 0], [1])]
    assert len(matched) == 3  # images 0 and 1, then 2 only, then none
    assert sorted(known.by_keyframe) == [0, 1, 2]
    for (points_2d, points_3d), (expected_2d, expected_3d) in zip(again, fresh, strict=True):
        assert len(points_2d) > 20
        np.testing.assert_array_equal(points_2d, expected_2d)
        np.testing.assert_array_equal(points_3d, expected_3d)
    other = extract_rootsift(synthetic_scene.views[0].image, 256)
    with pytest.raises(DataError, match="another query's features or another ratio"):
        index.correspondences(other, [0], 0.8, known)
    with pytest.raises(DataError, match="another query's features or another ratio"):
        index.correspondences(query, [0], 0.7, known)


def test_a_points_only_index_holds_only_keypoints_with_a_point(triangulated_structure):
    index = MatchIndex.of(triangulated_structure)
    counts = triangulated_structure.point_counts()
    assert np.array_equal(np.diff(index.offsets), counts)
    assert np.isfinite(index.points).all()
    assert index.codes.dtype == np.uint8 and len(index.codes) == counts.sum()
    every = MatchIndex.of(triangulated_structure, points_only=False)
    assert len(every.codes) == sum(len(f) for f in triangulated_structure.features)
    assert index.nbytes < every.nbytes
    with pytest.raises(ValueError):
        index.codes[0, 0] = 1  # read-only: a query cannot change the map


def test_a_points_only_index_localizes_the_query(synthetic_scene, depth_structure):
    index = MatchIndex.of(depth_structure)
    answer = localize_against(
        depth_structure,
        synthetic_scene.query_image,
        synthetic_scene.camera,
        [0, 1],
        match_index=index,
    )
    truth = synthetic_scene.query_pose
    assert answer.success
    assert np.linalg.norm(answer.pose.position - truth.position) < 0.01
    assert orientation_error_deg(answer.pose.quaternion, truth.quaternion) < 0.5


def test_an_index_of_another_map_is_refused(synthetic_scene, depth_structure):
    three = build_from_depth(synthetic_scene.views, max_features=256, quiet=True)
    with pytest.raises(DataError, match="match_index holds 3 images, the structure 2"):
        localize_against(
            depth_structure,
            synthetic_scene.query_image,
            synthetic_scene.camera,
            [0],
            match_index=MatchIndex.of(three),
        )


def test_sift_on_a_half_size_image_gives_keypoints_in_full_image_pixels():
    image = textured_image(seed=3, width=320, height=240)
    full = extract_rootsift(image, 2048)
    half = extract_rootsift(image, 2048, image_scale=0.5)
    assert 0 < len(half) < len(full)
    # Each half-size keypoint lies on a full-size one: the same corner, found at a
    # coarser scale, within about a full-size pixel.
    gaps = np.linalg.norm(half.keypoints[:, None] - full.keypoints[None], axis=2).min(axis=1)
    assert np.median(gaps) < 1.0
    assert half.keypoints[:, 0].max() > 160  # not left in half-size pixels


@pytest.mark.parametrize("scale", [0.0, -0.5, 1.5, float("nan"), "half", True])
def test_an_impossible_image_scale_is_named(scale):
    with pytest.raises(ConfigError, match="image_scale must be in \\(0, 1\\]"):
        extract_rootsift(textured_image(), 64, image_scale=scale)


def test_a_half_size_map_and_query_localize(synthetic_scene):
    structure = build_from_depth(
        synthetic_scene.views[:2], max_features=1024, quiet=True, image_scale=0.5
    )
    answer = localize_against(
        structure,
        synthetic_scene.query_image,
        synthetic_scene.camera,
        [0, 1],
        image_scale=0.5,
        match_index=MatchIndex.of(structure),
    )
    truth = synthetic_scene.query_pose
    assert answer.success
    assert np.linalg.norm(answer.pose.position - truth.position) < 0.02


def test_resized_pixels_map_back_through_pixel_centres():
    # Halved: the small image's pixel 0 covers full pixels 0 and 1, centred at 0.5;
    # its edge -0.5 is the full image's edge -0.5.
    small = np.array([[0.0, 0.0], [-0.5, -0.5], [10.0, 3.0]], dtype=np.float32)
    full = to_full_image(small, 2.0, 2.0)
    np.testing.assert_allclose(full, [[0.5, 0.5], [-0.5, -0.5], [20.5, 6.5]])
    np.testing.assert_allclose(to_full_image(small, 1.0, 1.0), small)


def test_an_index_refuses_keyframes_it_does_not_hold(depth_structure, synthetic_scene):
    query = extract_rootsift(synthetic_scene.query_image, 256)
    index = MatchIndex.of(depth_structure)
    for wrong in ([2], [-1]):
        with pytest.raises(DataError, match="not an image of the map"):
            index.correspondences(query, wrong, 0.8)
