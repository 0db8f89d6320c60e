"""The refine stage: what a PoseRefiner is given, and what its answer becomes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from relocfw import DataError, MapImage, Pose, PoseRefiner, Refined, Relocalizer
from relocfw.core.camera import PinholeCamera
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.report.evaluation import MethodResult, summarise

SHIFT = np.array([10.0, 0.0, 0.0])


class Recording(PoseRefiner):
    """Moves the network's pose by SHIFT, or falls back on every second query."""

    def __init__(self, fall_back_every_second: bool = False):
        self.fall_back_every_second = fall_back_every_second
        self.queries = []

    def fit(self, views, descriptors, quiet=True):
        self.views, self.descriptors = list(views), descriptors

    def refine(self, query):
        self.queries.append(query)
        if self.fall_back_every_second and len(self.queries) % 2 == 0:
            return Refined(query.network_pose, 3.0, True, {"solve": 0.002})
        moved = Pose(query.network_pose.position + SHIFT, query.network_pose.quaternion)
        return Refined(moved, 40.0, False, {"solve": 0.001})


@pytest.fixture
def scene(tiny_scene):
    train = load_sevenscenes(tiny_scene, None, "train")
    test = load_sevenscenes(tiny_scene, None, "test")
    return train, read_images(train, quiet=True), read_images(test, quiet=True)


def relocalizer(refiner):
    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.125, feature_dim=32)
    return Relocalizer(backbone, KMeansIndex(k=4), CentreCrop(), refiner=refiner)


def test_the_refiner_gets_the_map_and_answers_last(scene):
    frames, train, test = scene
    camera = PinholeCamera(40.0, 40.0, 24.0, 18.0, 48, 36)
    refiner = Recording()
    plain, refined = relocalizer(None), relocalizer(refiner)
    names = [f.name for f in frames]
    depths = [Path(f"/nowhere/{i}.depth.png") for i in range(len(frames))]
    poses = [f.pose for f in frames]
    described = [
        dataclasses.replace(f, camera=camera, depth_path=d, depth_units_per_metre=5000.0)
        for f, d in zip(frames, depths, strict=True)
    ]
    features = refined.fit(train, poses, frames=described)
    plain.fit(train, poses)
    assert [v.name for v in refiner.views] == names
    assert all(isinstance(v, MapImage) and v.camera == camera for v in refiner.views)
    assert [v.depth_path for v in refiner.views] == depths
    assert {v.depth_units_per_metre for v in refiner.views} == {5000.0}
    assert refiner.views[3].image is train[3] and refiner.views[3].pose == poses[3]
    assert np.array_equal(refiner.descriptors, features)

    before, after = plain.localize(test[0]), refined.localize(test[0], camera)
    (query,) = refiner.queries
    assert query.image is test[0] and query.camera == camera
    # The refiner sees the network's answer for the chosen crop, then has the last word.
    assert np.allclose(query.network_pose.position, before.pose.position)
    assert query.descriptor.shape == (32,)
    assert np.allclose(after.pose.position, before.pose.position + SHIFT)
    assert after.crop == before.crop and after.refine_confidence == 40.0
    assert not after.fell_back and after.refine_seconds == {"solve": 0.001}
    # Without a refiner nothing says it refined.
    assert np.isnan(before.refine_confidence) and not before.fell_back


def test_fallbacks_are_counted_in_the_summary(scene):
    frames, train, test = scene
    refiner = Recording(fall_back_every_second=True)
    pipeline = relocalizer(refiner)
    pipeline.fit(train, [f.pose for f in frames])
    answers = pipeline.localize_many(test, queries_at_once=2)
    assert [a.fell_back for a in answers] == [False, True, False, True]
    queries = load_sevenscenes(Path(frames[0].image_path).parents[1], None, "test")
    summary = summarise(MethodResult("refined", tuple(queries), tuple(answers)))
    assert summary["refine_fell_back"] == 2
    assert summary["refine_median_confidence"] == pytest.approx(21.5)
    assert summary["refine_median_ms_solve"] == pytest.approx(1.5)
    plain = [
        dataclasses.replace(a, refine_confidence=float("nan"), fell_back=False, refine_seconds={})
        for a in answers
    ]
    assert "refine_fell_back" not in summarise(MethodResult("plain", tuple(queries), tuple(plain)))
    # A refiner without confidence or fallback (refine=sequence) still reports its time.
    timed = [
        dataclasses.replace(a, refine_confidence=float("nan"), fell_back=False) for a in answers
    ]
    summary = summarise(MethodResult("timed", tuple(queries), tuple(timed)))
    assert summary["refine_median_ms_solve"] == pytest.approx(1.5)


def test_a_refiner_needs_the_map_poses_and_one_entry_per_image(scene):
    frames, train, _ = scene
    with pytest.raises(DataError, match="pose of every map image"):
        relocalizer(Recording()).fit(train)
    with pytest.raises(DataError, match=f"{len(train)} images but 2 frames"):
        relocalizer(Recording()).fit(train, [f.pose for f in frames], frames=frames[:2])
