"""The depth scale is judged over the map, not per frame: one close-range frame (a
camera facing a wall) loses its depth with one note and the build goes on, while a
map whose depth is all at a wrong scale is still refused naming a file; for
refine=features' depth map and for scene-coordinate training with depth alike."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from relocfw.core.errors import DataError
from relocfw.structure.depth_structure import build_from_depth, depth_of_view
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.scene_coordinate_buffer import BufferSettings, build_buffer
from tests.structure.scene_coordinate_room import room_views


def scaled_depth(view, factor: float, path):
    """The view with its depth PNG's readings times `factor`, written to `path`."""
    raw = cv2.imread(str(view.depth_path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), np.rint(raw * factor).astype(np.uint16))
    return dataclasses.replace(view, depth_path=path)


def test_one_close_range_frame_loses_its_depth_and_the_build_goes_on(
    synthetic_scene, tmp_path, capsys
):
    views = list(synthetic_scene.views)
    # About 3 m of wall read at 1/100: a median of 3 cm, below any sensor's range.
    views[1] = scaled_depth(views[1], 0.01, tmp_path / "close.depth.png")
    structure = build_from_depth(views, max_features=256, quiet=True)
    assert [v.name for v in structure.skipped_views] == ["view-1"]
    assert "median depth 0.03" in structure.skipped_views[0].reason
    assert not np.isfinite(structure.points[1]).any()
    for index in (0, 2):
        assert np.isfinite(structure.points[index]).all(axis=1).sum() > 100
    notes = [line for line in capsys.readouterr().err.splitlines() if "view-1" in line]
    assert len(notes) == 1 and str(tmp_path / "close.depth.png") in notes[0], notes


def test_a_map_whose_depth_is_all_at_a_wrong_scale_is_refused(synthetic_scene, tmp_path):
    views = [dataclasses.replace(view, depth_units_per_metre=1.0) for view in synthetic_scene.views]
    with pytest.raises(DataError, match=r"median depth 3\.\d+e\+03 m .*millimetres read as metres"):
        build_from_depth(views, max_features=64, quiet=True)


# build_from_depth(synthetic_scene.views, max_features=256) as the code before the
# map-wide depth scale (cdd3080) built it, with OpenCV 5.1: per view, the keypoints
# with a point and the sum of their coordinates.
BEFORE = [(256, 866.8886028472334), (256, 793.3055791463703), (256, 889.015332756564)]


def test_normal_depth_builds_the_same_map_as_before(synthetic_scene):
    built = build_from_depth(synthetic_scene.views, max_features=256, quiet=True)
    assert built.skipped_views == ()
    for view, features, points in zip(
        synthetic_scene.views, built.features, built.points, strict=True
    ):
        # Each view's keypoints lifted with its own depth map, as one view alone is.
        depth, reason = depth_of_view(view)
        assert reason == ""
        expected = lift_keypoints(features.keypoints, depth, view.camera, view.pose)
        assert points.dtype == np.float32  # the map keeps them as float32
        assert np.array_equal(points, expected.astype(np.float32), equal_nan=True)
    found = [
        (int(np.isfinite(p).all(axis=1).sum()), float(np.nansum(p, dtype=np.float64)))
        for p in built.points
    ]
    assert [count for count, _ in found] == [count for count, _ in BEFORE]
    assert [total for _, total in found] == pytest.approx([total for _, total in BEFORE], rel=1e-9)


def no_encoder(pixels: torch.Tensor) -> torch.Tensor:
    """Four zero channels per 8 x 8 cell: the buffer's cells without a network."""
    return torch.zeros(1, 4, pixels.shape[2] // 8, pixels.shape[3] // 8)


def test_scene_coordinate_training_judges_the_depth_scale_over_the_map(tmp_path, capsys):
    _, views = room_views(tmp_path)
    views[2] = scaled_depth(views[2], 0.01, tmp_path / "close.depth.png")
    settings = BufferSettings(
        image_size=120, passes=1, cells=2000, scale_jitter=0.0, brightness_jitter=0.0, seed=0
    )
    buffer = build_buffer(views, no_encoder, settings, use_depth=True)
    trained_on = set(buffer.views.tolist())
    assert trained_on == set(range(len(views))) - {2}  # its cells have no target
    assert torch.isfinite(buffer.points).all()
    notes = [line for line in capsys.readouterr().err.splitlines() if views[2].name in line]
    assert len(notes) == 1 and str(tmp_path / "close.depth.png") in notes[0], notes
    # The whole map at a wrong scale is still refused, naming a depth file.
    wrong = [dataclasses.replace(view, depth_units_per_metre=1.0) for view in views]
    with pytest.raises(DataError, match=r"median depth 3\.\d+e\+03 m .*millimetres read as metres"):
        build_buffer(wrong, no_encoder, settings, use_depth=True)
