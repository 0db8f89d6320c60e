"""Scorer.distance_scale: the unit that makes map distances comparable across models.

The expected scales are worked out by hand from a four-image map whose descriptors lie
on a line, so a slip in the fallback (reading each image's zero distance to itself,
forgetting to standardise) shows as a wrong number, not merely a positive one.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from relocfw.core.scorer import Scorer
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet

# Four map images on a line: dimension 2 is dimension 1 times ten, so after
# standardising both dimensions are the same and every distance is sqrt(2) times the
# one-dimensional distance.
LINE = np.array([0.0, 1.0, 3.0, 7.0])
MAP_DESCRIPTORS = np.column_stack([LINE, 10.0 * LINE])
# By hand: mean 2.75; squared deviations 7.5625, 3.0625, 0.0625, 18.0625 sum to
# 28.75, so the (population) spread is sqrt(28.75 / 4) = sqrt(7.1875).
SPREAD = math.sqrt(7.1875)


def scorer_with(index) -> Scorer:
    """A Scorer over a fitted map; distance_scale never runs the network."""
    index.fit(MAP_DESCRIPTORS)
    return Scorer(PoseNet(input_size=32, width=0.125, feature_dim=2), index)


def test_an_index_holding_the_images_falls_back_to_their_spacing():
    # The exhaustive index gives every map image 0. Nearest other image on the line:
    # 0 -> 1 (1), 1 -> 0 (1), 3 -> 1 (2), 7 -> 3 (4); median 1.5, standardised by the
    # spread, times sqrt(2) for the two equal dimensions.
    expected = math.sqrt(2.0) * 1.5 / SPREAD
    scale = scorer_with(ExhaustiveIndex()).distance_scale(MAP_DESCRIPTORS)
    assert scale == pytest.approx(expected, rel=1e-9)


def test_an_index_not_holding_the_images_uses_their_own_median_distance():
    # One k-means centre: the mean, the origin once standardised. Distances from it:
    # |x - 2.75| = 2.75, 1.75, 0.25, 4.25 (median 2.25), standardised, times sqrt(2).
    expected = math.sqrt(2.0) * 2.25 / SPREAD
    scale = scorer_with(KMeansIndex(k=1, n_init=1)).distance_scale(MAP_DESCRIPTORS)
    assert scale == pytest.approx(expected, rel=1e-9)


def test_a_map_of_identical_images_has_the_unit_scale():
    # No image has a distance to anything: there is no spacing to measure by.
    same = np.ones((4, 2))
    index = ExhaustiveIndex()
    index.fit(same)
    scorer = Scorer(PoseNet(input_size=32, width=0.125, feature_dim=2), index)
    assert scorer.distance_scale(same) == 1.0
