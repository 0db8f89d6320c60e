import numpy as np
import pytest
import torch

from relocfw import QueryOptions, Relocalizer
from relocfw.core.errors import ConfigError
from relocfw.core.interfaces import Backbone
from relocfw.core.values import Pose, PoseOutput
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.kmeans_index import KMeansIndex


class MeanColour(Backbone):
    """A toy backbone: the descriptor is the image's mean colour; the pose is junk."""

    input_size = 8
    feature_dim = 3

    def forward(self, images):
        features = images.mean(dim=(2, 3))
        n = len(images)
        return PoseOutput(torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), features)


def flat(colour):
    return np.full((8, 12, 3), colour, dtype=np.uint8)


def toy_map():
    images = [flat((250, 0, 0)), flat((0, 250, 0)), flat((0, 0, 250))]
    poses = [
        Pose([1.0, 0, 0], [1, 0, 0, 0]),
        Pose([0, 2.0, 0], [0, 1, 0, 0]),
        Pose([0, 0, 3.0], [0, 0, 1, 0]),
    ]
    return images, poses


def test_retrieval_answers_with_the_nearest_training_pose():
    images, poses = toy_map()
    relocalizer = Relocalizer(
        MeanColour(), ExhaustiveIndex(), CentreCrop(), QueryOptions(retrieval_k=1)
    )
    relocalizer.fit(images, poses)
    answer = relocalizer.localize(flat((10, 240, 5)))
    assert np.allclose(answer.pose.position, [0, 2, 0])
    assert np.allclose(answer.pose.quaternion, [0, 1, 0, 0])


def test_retrieval_k_weights_by_distance():
    images, poses = toy_map()
    relocalizer = Relocalizer(
        MeanColour(), ExhaustiveIndex(), CentreCrop(), QueryOptions(retrieval_k=2)
    )
    relocalizer.fit(images, poses)
    # Halfway between red and green in colour: halfway between their positions.
    answer = relocalizer.localize(flat((125, 125, 0)))
    assert np.allclose(answer.pose.position, [0.5, 1.0, 0.0], atol=1e-3)
    # Closer to red: closer to red's position.
    closer = relocalizer.localize(flat((200, 60, 0))).pose.position
    assert closer[0] > 0.5 and closer[1] < 1.0


def test_without_retrieval_the_network_pose_is_used():
    images, poses = toy_map()
    relocalizer = Relocalizer(MeanColour(), ExhaustiveIndex(), CentreCrop())
    relocalizer.fit(images, poses)
    assert np.allclose(relocalizer.localize(flat((0, 250, 0))).pose.position, 0)


def test_retrieval_needs_neighbours_and_poses():
    with pytest.raises(ConfigError, match="index=exhaustive"):
        Relocalizer(MeanColour(), KMeansIndex(k=2), CentreCrop(), QueryOptions(retrieval_k=1))
    images, _ = toy_map()
    relocalizer = Relocalizer(
        MeanColour(), ExhaustiveIndex(), CentreCrop(), QueryOptions(retrieval_k=1)
    )
    with pytest.raises(Exception, match="pose of every map image"):
        relocalizer.fit(images)


def test_exhaustive_neighbours_are_sorted():
    train = np.random.default_rng(0).normal(size=(20, 4))
    index = ExhaustiveIndex()
    index.fit(train)
    distances, indices = index.neighbours(train[:3] + 0.01, 5)
    assert distances.shape == indices.shape == (3, 5)
    assert np.all(np.diff(distances, axis=1) >= 0)
    assert list(indices[:, 0]) == [0, 1, 2]
