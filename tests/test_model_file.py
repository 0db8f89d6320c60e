"""Model files: a saved and reloaded Relocalizer answers exactly as the original."""

import numpy as np
import pytest
import torch

from relocfw import Relocalizer
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.model.model_file import load_model, save_model
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop


@pytest.fixture(scope="module")
def scene(tiny_scene):
    train = load_sevenscenes(tiny_scene, None, "train")
    test = load_sevenscenes(tiny_scene, None, "test")
    return train, read_images(train, quiet=True), read_images(test, quiet=True)


def tiny_backbone(**options):
    """A seeded tiny PoseNet and the options it was built with."""
    options = {"input_size": 32, "width": 0.0625, "feature_dim": 16, **options}
    torch.manual_seed(0)
    backbone = PoseNet(**options)
    # Training would set these; values away from the defaults show they are saved.
    backbone.set_position_normalisation(np.array([1.0, -2.0, 0.5]), 3.0)
    return backbone, options


def round_trip(relocalizer, options, tmp_path):
    path = save_model(tmp_path / "model.relocfw", relocalizer, options, {"scene": "tiny"})
    loaded = load_model(path)
    assert loaded.metadata == {"scene": "tiny"}
    return loaded


def answers(relocalizer, images):
    return [relocalizer.localize(image) for image in images]


def assert_same_answers(got, expected):
    for a, b in zip(got, expected, strict=True):
        assert a.crop == b.crop
        assert a.distance == pytest.approx(b.distance, rel=1e-9, abs=1e-12)
        assert np.allclose(a.pose.position, b.pose.position, rtol=1e-9, atol=1e-12)
        assert np.allclose(a.pose.quaternion, b.pose.quaternion, rtol=1e-9, atol=1e-12)
        assert np.array_equal(
            [a.position_spread, a.orientation_spread_deg],
            [b.position_spread, b.orientation_spread_deg],
            equal_nan=True,
        )


def test_retrieval_model_round_trip_answers_with_the_same_map_poses(scene, tmp_path):
    frames, train, test = scene
    backbone, options = tiny_backbone()
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop(), retrieval_k=2)
    relocalizer.fit(train, [f.pose for f in frames])
    loaded = round_trip(relocalizer, {"backbone": options}, tmp_path)
    assert loaded.retrieval_k == 2
    assert len(loaded.map_poses) == len(frames)
    for saved, original in zip(loaded.map_poses, frames, strict=True):
        assert np.allclose(saved.position, original.pose.position, rtol=0, atol=1e-12)
        assert np.allclose(saved.quaternion, original.pose.quaternion, rtol=0, atol=1e-12)
    expected = answers(relocalizer, test)
    assert_same_answers(answers(loaded, test), expected)
    # Retrieval really answered: the network's own pose of the same crop is elsewhere.
    network = Relocalizer(backbone, relocalizer.index, SweepCrop())
    own = answers(network, test)
    assert all(
        not np.allclose(a.pose.position, b.pose.position)
        for a, b in zip(expected, own, strict=True)
    )


def test_mc_sampling_model_round_trip_gives_the_same_poses_and_spreads(scene, tmp_path):
    frames, train, test = scene
    backbone, options = tiny_backbone(mc_samples=8)
    relocalizer = Relocalizer(backbone, KMeansIndex(k=3), CentreCrop(), sample_seed=7)
    relocalizer.fit(train)
    loaded = round_trip(relocalizer, {"backbone": options, "index": {"k": 3}}, tmp_path)
    assert loaded.backbone.mc_samples == 8 and loaded.sample_seed == 7
    expected = answers(relocalizer, test)
    assert all(np.isfinite(a.position_spread) and a.position_spread > 0 for a in expected)
    # The sample seed travels with the model file; torch's global stream plays no part.
    torch.manual_seed(123)
    assert_same_answers(answers(loaded, test), expected)
    # Sampling is live: another sample seed moves the answers.
    loaded.sample_seed = 8
    other = answers(loaded, test)
    assert not np.allclose(other[0].pose.position, expected[0].pose.position)


def test_a_model_trained_on_posenet_crops_is_loaded_with_its_crop_scale(scene, tmp_path):
    _, train_images, test_images = scene
    backbone, options = tiny_backbone()
    backbone.set_crop_scale(256 / 224)  # as training with train.crop_scale=1.142857 does
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop())
    relocalizer.fit(train_images)
    expected = answers(relocalizer, test_images)
    loaded = round_trip(relocalizer, {"backbone": options}, tmp_path)
    assert loaded.crop_scale == pytest.approx(256 / 224)
    assert_same_answers(answers(loaded, test_images), expected)
