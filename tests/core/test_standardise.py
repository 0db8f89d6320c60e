"""z-score scales (with their floor) and the chunked paths over a whole map."""

import numpy as np
import pytest

from relocfw.core.errors import DataError
from relocfw.core.standardise import (
    DEAD_FRACTION,
    ZScore,
    checked_descriptors,
    k_nearest,
    nearest,
    row_chunks,
)
from relocfw.plugins.exhaustive_index import ExhaustiveIndex


def map_with_a_near_dead_unit(seed=0):
    """50 map descriptors: three informative dimensions and one that barely moves.

    The near-dead unit (std about 1e-9, like a ReLU that almost never fires) is lowest
    on point 0, which is the query's neighbour in the informative dimensions.
    """
    rng = np.random.default_rng(seed)
    points = np.zeros((50, 4))
    points[:, :3] = rng.normal(size=(50, 3))
    points[:, 3] = 1e-9 * rng.normal(size=50)
    points[0, 3] = points[:, 3].min() - 1e-9
    query = points[0].copy()
    query[:3] += 0.01
    query[3] = points[:, 3].max() + 1e-6  # active on the query: 1e-6 above every map point
    return points, query[None]


def test_a_near_dead_unit_does_not_decide_the_nearest_neighbour():
    points, query = map_with_a_near_dead_unit()
    index = ExhaustiveIndex()
    index.fit(points)
    _, order = index.neighbours(query, len(points))
    informative = ZScore().fit(points[:, :3])
    _, expected = k_nearest(informative(query[:, :3]), informative(points[:, :3]), len(points))
    assert order[0, 0] == 0, "the near-dead unit chose the neighbour"
    assert np.array_equal(order, expected)


def test_a_near_dead_unit_is_scaled_like_a_typical_one():
    points, _ = map_with_a_near_dead_unit()
    zscore = ZScore().fit(points)
    spreads = points.std(axis=0)
    assert np.allclose(zscore.std[:3], spreads[:3], rtol=1e-12)
    assert zscore.std[3] == pytest.approx(np.median(spreads))


def test_dead_units_are_scaled_like_typical_ones_and_live_ones_keep_their_spread():
    rng = np.random.default_rng(1)
    points = rng.normal(size=(40, 6)) * [1.0, 2.0, 3.0, 1.0, 1.0, 1.0]
    points[:, 3] = 0.1  # not exactly representable: rounding leaves a std near 1e-17
    points[:, 4] = 0.0
    points[:, 5] *= 0.05  # a live unit with a small spread (5% of typical) keeps it
    zscore = ZScore().fit(points)
    spreads = points.std(axis=0)
    typical = np.median(spreads[[0, 1, 2, 5]])
    assert DEAD_FRACTION * typical < spreads[5] < typical
    assert zscore.std[3:5] == pytest.approx([typical, typical])
    assert np.allclose(zscore.std[[0, 1, 2, 5]], spreads[[0, 1, 2, 5]], rtol=1e-12)
    assert np.all(np.isfinite(zscore(points)))
    assert np.array_equal(ZScore().fit(np.full((6, 3), 0.1)).std, np.ones(3))


def test_a_unit_dead_on_the_map_that_fires_on_a_crop_weighs_like_a_typical_unit():
    # Half the units of a trained map can be dead (never fire on the map). A crop that
    # fires one of them by the typical spread is one z-unit from the map, as a crop off
    # by one typical spread in a live unit would be: not 100 (a 1% floor), not 0.1 (a
    # fixed scale of 1 where descriptors vary by about 0.1).
    rng = np.random.default_rng(2)
    points = np.zeros((60, 8))
    points[:, :4] = 0.1 * rng.normal(size=(60, 4))
    index = ExhaustiveIndex()
    index.fit(points)
    typical = np.median(points[:, :4].std(axis=0))
    crop = points[7].copy()
    crop[5] = typical  # fires a unit that is zero on every map image
    assert index.distance(crop[None])[0] == pytest.approx(1.0, rel=1e-9)


def test_row_chunks_cover_every_row_once_in_order():
    assert list(row_chunks(10, rows=4)) == [slice(0, 4), slice(4, 8), slice(8, 10)]
    assert list(row_chunks(8, rows=4)) == [slice(0, 4), slice(4, 8)]
    assert list(row_chunks(3)) == [slice(0, 3)]


def descriptors(n, d=6, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, d)) * rng.uniform(0.1, 10, size=d) + rng.uniform(-50, 50, d)


def test_zscore_fitted_in_many_chunks_equals_one_chunk():
    features = descriptors(101).astype(np.float32)
    whole = ZScore().fit(features, rows_at_a_time=len(features))
    chunked = ZScore().fit(features, rows_at_a_time=17)  # six full chunks and a short one
    assert np.allclose(chunked.mean, whole.mean, rtol=1e-12, atol=0)
    assert np.allclose(chunked.std, whole.std, rtol=1e-12, atol=0)
    assert np.allclose(whole.mean, features.astype(np.float64).mean(axis=0), rtol=1e-12)
    assert np.allclose(whole.std, features.astype(np.float64).std(axis=0), rtol=1e-9)


def test_non_finite_values_are_found_in_any_chunk():
    features = descriptors(20)
    features[17, 2] = np.nan  # in the fourth chunk of five rows
    with pytest.raises(DataError, match="NaN or infinity"):
        checked_descriptors(features, rows_at_a_time=5)


@pytest.mark.parametrize("k", [1, 3, 40])
def test_k_nearest_in_many_query_chunks_equals_one_chunk(k):
    points, queries = descriptors(40), descriptors(23, seed=1)
    one_d, one_i = k_nearest(queries, points, k, chunk=len(queries))
    many_d, many_i = k_nearest(queries, points, k, chunk=4)  # five full chunks and three rows
    assert np.array_equal(many_i, one_i)
    assert np.allclose(many_d, one_d, rtol=1e-12, atol=0)
    brute = np.linalg.norm(queries[:, None] - points[None], axis=2)
    assert np.array_equal(one_i, np.argsort(brute, axis=1, kind="stable")[:, :k])
    assert np.allclose(one_d, np.sort(brute, axis=1)[:, :k], rtol=1e-9)


def test_nearest_in_chunks_equals_brute_force():
    points, queries = descriptors(9), descriptors(10, seed=2)
    distances, indices = nearest(queries, points, chunk=3)
    brute = np.linalg.norm(queries[:, None] - points[None], axis=2)
    assert np.array_equal(indices, brute.argmin(axis=1))
    assert np.allclose(distances, brute.min(axis=1), rtol=1e-9)
