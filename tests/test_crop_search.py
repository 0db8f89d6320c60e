import numpy as np
import pytest

from relocfw.errors import ConfigError
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.ga_crop import GeneticCropSearch, chromosome_bits, decode
from relocfw.plugins.sweep_crop import SweepCrop
from relocfw.values import Crop


class Recorder:
    """A known distance over offsets that records every call and offset scored."""

    def __init__(self, function):
        self.function = function
        self.calls = []

    def __call__(self, crops):
        self.calls.append([c.x if c.y == 0 else c.y for c in crops])
        return np.array([self.function(offset) for offset in self.calls[-1]], dtype=float)

    @property
    def scored(self):
        return [o for call in self.calls for o in call]


def bowl(minimum, scale=5.0):
    return lambda offset: abs(offset - minimum) / scale


def test_chromosome_bits_follow_the_paper():
    # 2^(n-1) < w - h <= 2^n: 640 x 480 gives w - h = 160 and 8 bits.
    assert chromosome_bits(160) == 8
    assert chromosome_bits(128) == 7
    assert chromosome_bits(129) == 8
    assert chromosome_bits(1) == 1


def test_decode_reaches_both_edges():
    assert decode([1] * 8, 160) == 160
    assert decode([0] * 8, 160) == 0
    assert decode([1, 0, 0, 0, 0, 0, 0, 0], 160) == round(128 / 255 * 160)


def test_ga_finds_the_minimum_with_far_fewer_evaluations_than_the_sweep():
    errors, evaluations = [], []
    for seed in range(20):
        distance = Recorder(bowl(97))
        crop = GeneticCropSearch(seed=seed).search(640, 480, distance)
        errors.append(abs(crop.x - 97))
        evaluations.append(len(distance.scored))
    sweep = Recorder(bowl(97))
    assert SweepCrop().search(640, 480, sweep).x == 97
    # Paper defaults: at most 10 x (3 + 1) = 40 crops against the sweep's 161.
    assert max(evaluations) <= 40 < len(sweep.scored) == 161
    assert np.median(errors) <= 4  # within 4 px of 160, on a typical run
    # Given more generations the GA lands on the exact minimum, still far under 161.
    distance = Recorder(bowl(97))
    crop = GeneticCropSearch(population=10, iterations=12, seed=1).search(640, 480, distance)
    assert crop.x == 97
    assert len(distance.scored) < 100


def test_ga_scores_each_offset_once_and_batches_each_generation():
    distance = Recorder(bowl(30))
    GeneticCropSearch(population=10, iterations=3, seed=0).search(640, 480, distance)
    assert len(distance.scored) == len(set(distance.scored))
    assert len(distance.calls) <= 4  # one batch per generation at most
    assert all(0 <= o <= 160 for o in distance.scored)


def test_ga_is_seeded():
    first = GeneticCropSearch(seed=7).search(640, 480, Recorder(bowl(50)))
    second = GeneticCropSearch(seed=7).search(640, 480, Recorder(bowl(50)))
    assert first == second


def test_ga_searches_y_for_portrait_images():
    distance = Recorder(bowl(40))
    crop = GeneticCropSearch(iterations=10, seed=0).search(300, 400, distance)
    assert crop.x == 0 and crop.size == 300 and abs(crop.y - 40) <= 5


def test_square_image_needs_no_search():
    distance = Recorder(bowl(0))
    assert GeneticCropSearch().search(100, 100, distance) == Crop(0, 0, 100)
    assert distance.calls == []


def test_sweep_finds_the_exact_minimum_of_an_arbitrary_function():
    values = np.random.default_rng(0).normal(size=161)
    distance = Recorder(lambda offset: values[offset])
    assert SweepCrop().search(640, 480, distance).x == int(np.argmin(values))
    assert sorted(distance.scored) == list(range(161))
    assert len(distance.calls) == 1


def test_sweep_stride_keeps_the_far_edge():
    distance = Recorder(bowl(160))
    assert SweepCrop(stride=50).search(640, 480, distance).x == 160
    assert distance.scored == [0, 50, 100, 150, 160]


def test_centre_crop_never_scores():
    distance = Recorder(bowl(0))
    assert CentreCrop().search(640, 480, distance) == Crop(80, 0, 480)
    assert distance.calls == []


@pytest.mark.parametrize(
    "options, key",
    [
        ({"population": 1}, "population"),
        ({"crossover": 1.5}, "crossover"),
        ({"mutation": -0.1}, "mutation"),
        ({"iterations": -1}, "iterations"),
        ({"population": "ten"}, "population"),
    ],
)
def test_bad_ga_options_name_the_key(options, key):
    with pytest.raises(ConfigError, match=key):
        GeneticCropSearch(**options)


def test_bad_sweep_stride():
    with pytest.raises(ConfigError, match="stride"):
        SweepCrop(stride=0)
