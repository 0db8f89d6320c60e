import numpy as np
import pytest
import torch

from relocfw import Crop, QueryOptions, Relocalizer
from relocfw.core.imaging import Strip
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop


class CountingPoseNet(PoseNet):
    """Counts forward passes and the inputs they carried."""

    def __init__(self):
        torch.manual_seed(0)
        super().__init__(input_size=32, width=0.125, feature_dim=32)
        self.batches = []

    def forward(self, images):
        self.batches.append(len(images))
        return super().forward(images)


@pytest.fixture
def scene_images(tiny_scene):
    train = load_sevenscenes(tiny_scene, None, "train")
    test = load_sevenscenes(tiny_scene, None, "test")
    return read_images(train, quiet=True), read_images(test, quiet=True)


def test_ga_scores_one_batch_per_generation_and_never_twice(scene_images):
    train, test = scene_images
    backbone = CountingPoseNet()
    relocalizer = Relocalizer(backbone, KMeansIndex(k=4), GeneticCropSearch(seed=0))
    relocalizer.fit(train)
    backbone.batches.clear()
    answer = relocalizer.localize(test[0])
    # 48x36 image -> 43x32 strip: 12 windows, at most 4 generations -> 4 passes.
    assert len(backbone.batches) <= 4
    assert sum(backbone.batches) == answer.evaluations <= 12
    assert answer.crop.size == 36 and 0 <= answer.crop.x <= 12 and answer.crop.y == 0
    assert np.isclose(np.linalg.norm(answer.pose.quaternion), 1.0)


def test_sweep_picks_the_window_with_the_smallest_distance(scene_images):
    train, test = scene_images
    relocalizer = Relocalizer(
        CountingPoseNet(), ExhaustiveIndex(), SweepCrop(), QueryOptions(batch_size=5)
    )
    relocalizer.fit(train)
    image = test[1]
    strip = Strip(image, 32)
    windows = sorted({strip.window(Crop(x, 0, 36)) for x in range(13)})
    batch = torch.stack([strip.cut(w) for w in windows])
    features = relocalizer.scorer.forward(batch).features
    distances = relocalizer.index.distance(features)
    answer = relocalizer.localize(image)
    assert strip.window(answer.crop) == windows[int(np.argmin(distances))]
    assert answer.distance == pytest.approx(distances.min())
    assert answer.evaluations == len(windows)


def test_centre_crop_is_one_pass_and_fit_uses_centre_crops(scene_images):
    train, test = scene_images
    backbone = CountingPoseNet()
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), CentreCrop())
    features = relocalizer.fit(train)
    assert features.shape == (len(train), 32)
    backbone.batches.clear()
    answer = relocalizer.localize(train[3])
    assert backbone.batches == [1]
    # The training image's own centre crop is in the map: distance zero.
    assert answer.distance == pytest.approx(0.0, abs=1e-6)
    assert answer.crop == Crop(6, 0, 36)


def test_localize_is_deterministic(scene_images):
    train, test = scene_images
    relocalizer = Relocalizer(CountingPoseNet(), KMeansIndex(k=3), GeneticCropSearch(seed=2))
    relocalizer.fit(train)
    first, second = relocalizer.localize(test[2]), relocalizer.localize(test[2])
    assert first.crop == second.crop
    assert np.array_equal(first.pose.position, second.pose.position)
