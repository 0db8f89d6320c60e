import numpy as np
import pytest

from relocfw.errors import ConfigError, DataError
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.standardise import ZScore, nearest


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


def test_kmeans_with_fewer_clusters_is_never_closer_than_exact():
    train, queries = descriptors(60), descriptors(20, seed=2)
    kmeans, exhaustive = KMeansIndex(k=5), ExhaustiveIndex()
    kmeans.fit(train)
    exhaustive.fit(train)
    # Centres are means, not members: a query can be closer to a centre. On training
    # descriptors themselves the exact index gives zero, k-means not.
    assert np.allclose(exhaustive.distance(train), 0, atol=1e-6)
    assert kmeans.distance(train).mean() > 0.5
    assert kmeans.distance(queries).shape == (20,)


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


def test_nearest_works_in_chunks():
    points, queries = descriptors(3), descriptors(5, seed=4)
    distances, _ = nearest(queries, points)
    assert np.allclose(distances, np.linalg.norm(queries[:, None] - points[None], axis=2).min(1))


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
