"""Mutual nearest neighbours with the ratio test, against a brute-force reference."""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.structure.features import LocalFeatures
from relocfw.structure.matching import match_against_views, mutual_nearest_neighbours


def brute_force(query: np.ndarray, candidates: np.ndarray, ratio: float) -> np.ndarray:
    """The definition, pair by pair in float64: nearest candidate j of each query
    descriptor i, kept if i is j's nearest and d1 / d2 < ratio."""
    query = query.astype(np.float64)
    candidates = candidates.astype(np.float64)
    pairs = []
    for i, descriptor in enumerate(query):
        distances = np.sqrt(((candidates - descriptor) ** 2).sum(axis=1))
        if len(distances) < 2:
            continue
        first, second = np.argsort(distances, kind="stable")[:2]
        back = np.sqrt(((query - candidates[first]) ** 2).sum(axis=1))
        if np.argmin(back) == i and distances[first] < ratio * distances[second]:
            pairs.append((i, first))
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def related_descriptors(seed: int, count: int, others: int, dim: int = 128):
    """Query rows, and candidates holding noisy copies of some of them plus random
    rows, so some pairs pass the ratio test and many do not (unit norm, as RootSIFT)."""
    rng = np.random.default_rng(seed)
    query = rng.random((count, dim)).astype(np.float32)
    copies = query[rng.permutation(count)[: count // 2]] + rng.normal(0, 0.05, (count // 2, dim))
    candidates = np.concatenate([copies, rng.random((others, dim))]).astype(np.float32)
    candidates = candidates[rng.permutation(len(candidates))]
    query /= np.linalg.norm(query, axis=1, keepdims=True)
    candidates /= np.linalg.norm(candidates, axis=1, keepdims=True)
    return query, candidates


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("ratio", [0.8, 0.95, 1.0])
def test_equals_the_brute_force_reference(seed, ratio):
    query, candidates = related_descriptors(seed, 120, 150)
    matches = mutual_nearest_neighbours(query, candidates, ratio=ratio)
    expected = brute_force(query, candidates, ratio)
    assert matches.dtype == np.int64 and matches.shape[1] == 2
    assert np.array_equal(matches, expected)
    assert 0 < len(expected) < len(query)  # the reference is not trivially empty or full


def test_the_ratio_test_decides_on_random_descriptors():
    # Unrelated random rows: many mutual pairs, few distinctive ones.
    rng = np.random.default_rng(3)
    query, candidates = rng.random((200, 16)), rng.random((300, 16))
    loose = mutual_nearest_neighbours(query, candidates, ratio=1.0)
    strict = mutual_nearest_neighbours(query, candidates, ratio=0.7)
    assert np.array_equal(loose, brute_force(query, candidates, 1.0))
    assert np.array_equal(strict, brute_force(query, candidates, 0.7))
    assert len(strict) < len(loose)


@pytest.mark.parametrize("count, others", [(0, 5), (5, 0), (0, 0), (5, 1), (1, 1)])
def test_empty_and_single_candidate_inputs_give_no_matches(count, others):
    rng = np.random.default_rng(4)
    matches = mutual_nearest_neighbours(rng.random((count, 8)), rng.random((others, 8)))
    assert matches.shape == (0, 2) and matches.dtype == np.int64


def test_one_query_descriptor_can_match():
    candidates = np.eye(4, dtype=np.float32)
    matches = mutual_nearest_neighbours(candidates[2:3] + 0.01, candidates)
    assert matches.tolist() == [[0, 2]]


def test_match_against_views_equals_matching_each_view_alone():
    rng = np.random.default_rng(5)
    query, pool = related_descriptors(6, 100, 200)
    sizes = [0, 1, 60, 90, 49]  # an empty view and a one-row view among them
    views, start = [], 0
    for size in sizes:
        views.append(LocalFeatures(rng.random((size, 2)) * 100, pool[start : start + size]))
        start += size
    features = LocalFeatures(rng.random((len(query), 2)) * 100, query)
    results = match_against_views(features, views, ratio=0.9)
    assert [number for number, _ in results] == list(range(len(views)))
    for (_, pairs), view in zip(results, views, strict=True):
        assert np.array_equal(pairs, brute_force(query, view.descriptors, 0.9))
    assert sum(len(pairs) for _, pairs in results) > 0
    assert match_against_views(features, []) == []


def test_mismatched_descriptors_and_bad_ratios_raise_one_error():
    rng = np.random.default_rng(7)
    with pytest.raises(DataError, match="query descriptors have 8 dimensions, candidates 9"):
        mutual_nearest_neighbours(rng.random((3, 8)), rng.random((3, 9)))
    with pytest.raises(DataError, match="candidates must be an \\[N, D\\]"):
        mutual_nearest_neighbours(rng.random((3, 8)), rng.random(8))
    with pytest.raises(DataError, match="query holds NaN"):
        mutual_nearest_neighbours(np.full((3, 8), np.nan), rng.random((3, 8)))
    for ratio in (0.0, 1.5, float("nan"), "x"):
        with pytest.raises(ConfigError, match="ratio"):
            mutual_nearest_neighbours(rng.random((3, 8)), rng.random((3, 8)), ratio=ratio)
    query = LocalFeatures(np.zeros((2, 2)), rng.random((2, 8)))
    with pytest.raises(DataError, match=r"views\[1\] has 9-dimensional"):
        match_against_views(query, [query, LocalFeatures(np.zeros((2, 2)), rng.random((2, 9)))])
