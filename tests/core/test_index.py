import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.standardise import ZScore, nearest
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.kmeans_index import KMeansIndex


def descriptors(n, d=16, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, d)) * rng.uniform(0.1, 10, size=d) + rng.normal(size=d)


def test_kmeans_equals_exhaustive_when_k_is_the_number_of_descriptors():
    train = descriptors(30)
    queries = descriptors(50, seed=1)
    kmeans = KMeansIndex(k=30, seed=0, n_init=1)
    exhaustive = ExhaustiveIndex()
    kmeans.fit(train)
    exhaustive.fit(train)
    assert np.allclose(kmeans.distance(queries), exhaustive.distance(queries), atol=1e-9)


def test_kmeans_distance_is_to_the_nearest_centre_so_map_descriptors_are_not_at_zero():
    train, queries = descriptors(60), descriptors(20, seed=2)
    kmeans, exhaustive = KMeansIndex(k=5), ExhaustiveIndex()
    kmeans.fit(train)
    exhaustive.fit(train)
    z = ZScore().fit(train)
    to_centres = np.linalg.norm(z(queries)[:, None] - kmeans.centres[None], axis=2)
    assert np.allclose(kmeans.distance(queries), to_centres.min(axis=1), rtol=1e-12)
    assert np.array_equal(kmeans.assign(queries), to_centres.argmin(axis=1))
    # Centres are means of their cluster, not members: on the map's own descriptors
    # the exact index gives zero and k-means does not. (Between the map's points a
    # query can be closer to a centre than to any descriptor, so neither index's
    # distance bounds the other's in general.)
    assert np.allclose(exhaustive.distance(train), 0, atol=1e-6)
    assert np.all(kmeans.distance(train) > 0.1)


def test_exhaustive_nearest_matches_brute_force():
    train, queries = descriptors(40), descriptors(7, seed=3)
    index = ExhaustiveIndex()
    index.fit(train)
    z = ZScore().fit(train)
    brute = np.linalg.norm(z(queries)[:, None] - z(train)[None], axis=2)
    distances, indices = index.nearest(queries)
    assert np.array_equal(indices, brute.argmin(axis=1))
    assert np.allclose(distances, brute.min(axis=1))


def test_zscore_standardises_and_survives_constant_dimensions():
    train = descriptors(100)
    train[:, 3] = 5.0
    z = ZScore().fit(train)(train)
    assert np.allclose(np.delete(z, 3, axis=1).mean(0), 0, atol=1e-9)
    assert np.allclose(np.delete(z, 3, axis=1).std(0), 1)
    assert np.all(np.isfinite(z))


def test_nearest_is_the_smallest_euclidean_distance_in_one_or_many_chunks():
    points, queries = descriptors(3), descriptors(5, seed=4)
    brute = np.linalg.norm(queries[:, None] - points[None], axis=2)
    for chunk in (None, 2):  # one chunk of five queries; three chunks
        distances, indices = nearest(queries, points, chunk=chunk)
        assert np.allclose(distances, brute.min(1), rtol=1e-9)
        assert np.array_equal(indices, brute.argmin(1))


def test_bad_k():
    with pytest.raises(ConfigError, match="k must be at least 1"):
        KMeansIndex(k=0)
    with pytest.raises(ConfigError, match="k=50 is more clusters than training descriptors"):
        KMeansIndex(k=50).fit(descriptors(10))


def test_bad_descriptors_and_unfitted_use():
    with pytest.raises(DataError, match="NaN"):
        ExhaustiveIndex().fit(np.full((3, 4), np.nan))
    with pytest.raises(DataError, match="not fitted"):
        KMeansIndex(k=2).distance(descriptors(2))
    index = ExhaustiveIndex()
    index.fit(descriptors(5, d=8))
    with pytest.raises(DataError, match="dimensions"):
        index.distance(descriptors(2, d=9))
