"""Correspondences per point: a query keypoint matched in several keyframes gives one
2-D/3-D row (its best match), so inliers and confidence count distinct evidence."""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.core.values import Pose
from relocfw.structure.features import LocalFeatures
from relocfw.structure.matching import one_match_per_query
from relocfw.structure.query_solver import correspondences_of, localize_against
from relocfw.structure.structure_map import StructureMap

CAMERA = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)


def unit_rows(rng: np.random.Generator, count: int) -> np.ndarray:
    rows = rng.uniform(0.0, 1.0, (count, 128)).astype(np.float32)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def test_the_best_match_of_each_query_keypoint_is_kept_ties_to_the_earlier_row():
    query = np.array([4, 1, 4, 2, 1, 4])
    distances = np.array([0.5, 0.3, 0.2, 0.7, 0.3, 0.2])
    kept = one_match_per_query(query, distances)
    # keypoint 1: rows 1 and 4 tie, row 1 first; 2: row 3; 4: rows 2 and 5 tie at 0.2.
    assert kept.tolist() == [1, 3, 2]
    assert one_match_per_query(np.zeros(0), np.zeros(0)).tolist() == []
    with pytest.raises(DataError, match="3 query indices but 2 distances"):
        one_match_per_query(np.array([0, 1, 2]), np.array([0.1, 0.2]))


def duplicated_map(rng: np.random.Generator) -> tuple[StructureMap, LocalFeatures, np.ndarray]:
    """Three keyframes holding the same 40 descriptors (with different small noise)
    and the same 3-D points: every query keypoint matches in all three."""
    descriptors = unit_rows(rng, 40)
    points = rng.uniform([-1, -1, 2], [1, 1, 4], (40, 3)).astype(np.float32)
    pixels = points[:, :2] / points[:, 2:] * CAMERA.fx + [CAMERA.cx, CAMERA.cy]
    features, clouds = [], []
    for noise in (0.02, 0.005, 0.03):  # keyframe 1 is the closest match of every keypoint
        noisy = descriptors + rng.normal(0, noise, descriptors.shape).astype(np.float32)
        features.append(LocalFeatures(pixels, noisy))
        clouds.append(points + np.float32(noise))  # tells which keyframe a row came from
    pose = Pose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    structure = StructureMap(
        features=tuple(features),
        points=tuple(clouds),
        poses=(pose,) * 3,
        cameras=(CAMERA,) * 3,
        names=("a", "b", "c"),
        source="depth",
    )
    return structure, LocalFeatures(pixels, descriptors), points


def test_duplicate_correspondences_count_once():
    structure, query, points = duplicated_map(np.random.default_rng(0))
    image, world = correspondences_of(structure, query, [0, 1, 2], ratio=0.8)
    assert len(image) == len(world) == 40  # not 120: one row per query keypoint
    assert np.allclose(image, query.keypoints)  # in query keypoint order
    assert np.allclose(world, points + np.float32(0.005))  # each from keyframe 1, its best
    # The solver's inliers count keypoints too: 40 points, exactly seen, 40 inliers.
    answer = localize_against(
        structure, None, CAMERA, [0, 1, 2], min_inliers=4, query_features=query
    )
    assert answer.success and answer.correspondences == 40 and answer.inliers <= 40
    assert answer.inliers >= 38


def test_a_keypoint_whose_best_match_has_no_point_keeps_a_match_that_has_one():
    structure, query, points = duplicated_map(np.random.default_rng(1))
    clouds = list(structure.points)
    clouds[1] = np.full_like(clouds[1], np.nan)  # the best keyframe has no 3-D points
    without = StructureMap(
        structure.features,
        tuple(clouds),
        structure.poses,
        structure.cameras,
        structure.names,
        "triangulated",
    )
    _, world = correspondences_of(without, query, [0, 1, 2], ratio=0.8)
    assert len(world) == 40 and np.allclose(world, points + np.float32(0.02))
