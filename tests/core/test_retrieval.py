"""refine=retrieval: the nearest map images' poses, with any index."""

import numpy as np
import pytest
import torch

from relocfw import ConfigError, DataError, MapImage, QueryOptions, RefineQuery, Relocalizer
from relocfw.core.interfaces import Backbone
from relocfw.core.values import Pose, PoseOutput
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.retrieval_refiner import RetrievalRefiner, weighted_mean_pose


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


def retrieval(k=1, index=None):
    return Relocalizer(
        MeanColour(), index or ExhaustiveIndex(), CentreCrop(), refiner=RetrievalRefiner(k)
    )


@pytest.mark.parametrize(
    "index", [ExhaustiveIndex(), KMeansIndex(k=2)], ids=["exhaustive", "kmeans"]
)
def test_k_1_answers_with_the_nearest_map_pose_with_any_index(index):
    images, poses = toy_map()
    relocalizer = retrieval(1, index)
    relocalizer.fit(images, poses)
    answer = relocalizer.localize(flat((10, 240, 5)))
    assert np.allclose(answer.pose.position, [0, 2, 0])
    assert np.allclose(answer.pose.quaternion, [0, 1, 0, 0])
    # It never falls back; its confidence is minus the distance to the nearest map image.
    assert not answer.fell_back
    assert answer.refine_confidence < 0
    exact = retrieval(1, ExhaustiveIndex())
    exact.fit(images, poses)
    nearest = exact.index.distance(exact.describe([flat((10, 240, 5))]))[0]
    assert answer.refine_confidence == pytest.approx(-nearest, rel=1e-12)
    assert set(answer.refine_seconds) == {"retrieval"}


def test_k_2_weights_by_distance():
    images, poses = toy_map()
    relocalizer = retrieval(2)
    relocalizer.fit(images, poses)
    # Halfway between red and green in colour: halfway between their positions.
    answer = relocalizer.localize(flat((125, 125, 0)))
    assert np.allclose(answer.pose.position, [0.5, 1.0, 0.0], atol=1e-3)
    # Closer to red: closer to red's position.
    closer = relocalizer.localize(flat((200, 60, 0))).pose.position
    assert closer[0] > 0.5 and closer[1] < 1.0


def test_the_weights_are_inverse_distances():
    poses = [Pose([0.0, 0, 0], [1, 0, 0, 0]), Pose([3.0, 0, 0], [1, 0, 0, 0])]
    # Distances 1 and 2: weights 2/3 and 1/3 (up to the 1e-6 that guards a 0).
    assert np.allclose(weighted_mean_pose(poses, np.array([1.0, 2.0])).position, [1, 0, 0])
    exact = weighted_mean_pose(poses, np.array([0.0, 2.0])).position
    assert exact[0] == pytest.approx(0.0, abs=1e-5)


def test_without_a_refiner_the_network_pose_is_used():
    images, poses = toy_map()
    relocalizer = Relocalizer(MeanColour(), ExhaustiveIndex(), CentreCrop())
    relocalizer.fit(images, poses)
    assert np.allclose(relocalizer.localize(flat((0, 250, 0))).pose.position, 0)


def test_retrieval_needs_poses_and_a_k_of_at_least_1():
    with pytest.raises(ConfigError, match="refine.k must be at least 1, got 0"):
        RetrievalRefiner(0)
    with pytest.raises(ConfigError, match="refine.k must be an integer"):
        RetrievalRefiner(1.5)
    images, _ = toy_map()
    with pytest.raises(DataError, match="pose of every map image"):
        retrieval().fit(images)
    with pytest.raises(ConfigError, match="not fitted"):
        RetrievalRefiner().refine(RefineQuery(flat(0), Pose([0, 0, 0], [1, 0, 0, 0]), np.ones(3)))


def test_retrieval_refuses_sampling_the_network_pose():
    with pytest.raises(ConfigError, match="never answers with the network's pose") as refused:
        Relocalizer(
            MeanColour(),
            ExhaustiveIndex(),
            CentreCrop(),
            QueryOptions(crop_samples=2),
            refiner=RetrievalRefiner(),
        )
    assert "query.crop_samples=2" in str(refused.value)


def random_map(count=30, dim=6, seed=0):
    rng = np.random.default_rng(seed)
    # Spreads that differ per dimension, and one dead unit: the z-scores matter.
    descriptors = rng.normal(size=(count, dim)) * np.array([1, 5, 0.1, 2, 1e-9, 3])
    quaternions = rng.normal(size=(count, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    views = [
        MapImage(f"map {i}", flat(0), Pose(rng.normal(size=3), q))
        for i, q in enumerate(quaternions)
    ]
    return views, descriptors, rng.normal(size=(5, dim)) * np.array([1, 5, 0.1, 2, 1e-9, 3])


def test_the_neighbours_are_index_exhaustive_s():
    views, descriptors, queries = random_map()
    refiner, index = RetrievalRefiner(k=3), ExhaustiveIndex()
    refiner.fit(views, descriptors)
    index.fit(descriptors)
    for descriptor in queries:
        query = RefineQuery(flat(0), views[0].pose, descriptor)
        distances, indices = index.neighbours(descriptor[None], 3)
        expected = weighted_mean_pose([views[i].pose for i in indices[0]], distances[0])
        got = refiner.refine(query)
        assert np.array_equal(got.pose.position, expected.position)
        assert np.array_equal(got.pose.quaternion, expected.quaternion)
        assert got.confidence == -distances[0, 0]


def test_a_stored_refiner_answers_as_the_fitted_one():
    views, descriptors, queries = random_map()
    fitted = RetrievalRefiner(k=2)
    fitted.fit(views, descriptors)
    loaded = RetrievalRefiner(k=2)
    loaded.load_state(fitted.state())
    # A model file before refine=retrieval held index=exhaustive's state and the poses.
    index = ExhaustiveIndex()
    index.fit(descriptors)
    poses = torch.tensor([[*v.pose.position, *v.pose.quaternion] for v in views])
    from_index = RetrievalRefiner(k=2)
    from_index.load_state({**index.state(), "poses": poses})
    for descriptor in queries:
        query = RefineQuery(flat(0), views[0].pose, descriptor)
        expected = fitted.refine(query)
        for other in (loaded, from_index):
            answer = other.refine(query)
            assert np.array_equal(answer.pose.position, expected.pose.position)
            assert np.array_equal(answer.pose.quaternion, expected.pose.quaternion)
    assert fitted.saves_state
    with pytest.raises(DataError, match="30 map descriptors but poses of shape"):
        RetrievalRefiner().load_state({**fitted.state(), "poses": poses[:3]})


def test_a_stored_refiner_keeps_its_k_without_its_options():
    views, descriptors, queries = random_map()
    fitted = RetrievalRefiner(k=3)
    fitted.fit(views, descriptors)
    loaded = RetrievalRefiner()  # a caller who saved without the refiner's options
    loaded.load_state(fitted.state())
    assert loaded.k == 3
    query = RefineQuery(flat(0), views[0].pose, queries[0])
    assert np.array_equal(loaded.refine(query).pose.position, fitted.refine(query).pose.position)


def test_query_options_are_keyword_only():
    with pytest.raises(TypeError):
        QueryOptions(16)


def test_exhaustive_neighbours_are_sorted():
    train = np.random.default_rng(0).normal(size=(20, 4))
    index = ExhaustiveIndex()
    index.fit(train)
    distances, indices = index.neighbours(train[:3] + 0.01, 5)
    assert distances.shape == indices.shape == (3, 5)
    assert np.all(np.diff(distances, axis=1) >= 0)
    assert list(indices[:, 0]) == [0, 1, 2]
