import numpy as np
from relocfw_coarse_to_fine.search import CoarseToFineCrop

from relocfw.core.contracts import check_crop_search


def test_keeps_relocfw_contract():
    check_crop_search(CoarseToFineCrop())


def test_finds_the_minimum_of_a_bowl_with_few_crops():
    scored = []

    def distance(crops):
        scored.extend(c.x for c in crops)
        return np.array([abs(c.x - 97) for c in crops], dtype=float)

    assert CoarseToFineCrop().search(640, 480, distance).x == 97
    assert len(scored) < 40
