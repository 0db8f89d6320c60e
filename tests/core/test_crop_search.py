import numpy as np
import pytest
import torch

from relocfw.core.errors import ConfigError
from relocfw.core.imaging import image_fingerprint
from relocfw.core.interfaces import CropSearch, crop_at, query_seed
from relocfw.core.pipeline import Relocalizer
from relocfw.core.query_windows import QueryWindows
from relocfw.core.values import Crop
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import (
    GeneticCropSearch,
    chromosome_bits,
    decode,
    offset_of,
    roulette,
)
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop


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
    # 2^(n-1) < w - h < 2^n: 640 x 480 gives w - h = 160 and 8 bits; where the span
    # is a power of two, the n with 2^n > span (1024 x 768: 256 -> 9 bits).
    assert chromosome_bits(160) == 8
    assert chromosome_bits(127) == 7
    assert chromosome_bits(128) == 8
    assert chromosome_bits(129) == 8
    assert chromosome_bits(255) == 8
    assert chromosome_bits(256) == 9
    assert chromosome_bits(1) == 1


def test_every_offset_is_the_decode_of_some_chromosome():
    for span in range(1, 2001):
        bits = chromosome_bits(span)
        reachable = np.unique(offset_of(np.arange(2**bits), bits, span))
        assert np.array_equal(reachable, np.arange(span + 1)), f"span {span}, {bits} bits"
    # offset_of is the bit-string decode, value for value.
    for span, bits in ((160, 8), (256, 9), (7, 3)):
        for value in range(2**bits):
            chromosome = [int(b) for b in format(value, f"0{bits}b")]
            assert decode(chromosome, span) == offset_of(value, bits, span)


def test_1024_wide_images_can_choose_the_centre_crop():
    # 1024 x 768: span 256, centre offset 128; with 8 bits no chromosome decoded to it.
    bits = chromosome_bits(256)
    assert 128 in set(offset_of(np.arange(2**bits), bits, 256).tolist())


def test_roulette_draws_in_proportion_to_fitness():
    fitness = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    draws = roulette(fitness, 50_000, np.random.default_rng(0))
    shares = np.bincount(draws, minlength=5) / len(draws)
    assert shares[0] == 0  # no fitness, never a parent
    # Binomial standard error at 50 000 draws is at most 0.0023.
    assert np.allclose(shares, fitness / fitness.sum(), atol=0.01)


def test_ga_beats_random_sampling_with_the_same_budget():
    # On a unimodal distance, selection by fitness should concentrate the search near
    # the minimum: over many seeds and minima, the GA's answer is closer than the best
    # of as many distinct offsets drawn at random. A GA that ignores fitness is not.
    ga_errors, random_errors = [], []
    for seed in range(300):
        minimum = (seed * 37) % 161
        distance = Recorder(bowl(minimum))
        crop = GeneticCropSearch(seed=seed).search(640, 480, distance)
        ga_errors.append(abs(crop.x - minimum))
        budget = len(set(distance.scored))
        sample = np.random.default_rng(10_000 + seed).choice(161, size=budget, replace=False)
        random_errors.append(np.abs(sample - minimum).min())
    assert np.mean(ga_errors) < 0.8 * np.mean(random_errors)


def test_each_query_gets_its_own_stream_and_the_same_query_the_same_one():
    class Seeded:
        def __init__(self, distance, query_seed):
            self.distance, self.query_seed = distance, query_seed

        def __call__(self, crops):
            return self.distance(crops)

    def first_generation(query_seed, seed=3):
        distance = Recorder(bowl(50))
        GeneticCropSearch(seed=seed).search(640, 480, Seeded(distance, query_seed))
        return distance.calls[0]

    assert first_generation(11) == first_generation(11)
    assert first_generation(11) != first_generation(12)
    # The search's own seed still matters for a fixed query.
    assert first_generation(11, seed=1) != first_generation(11, seed=2)


def test_the_query_seed_is_the_image_fingerprint_computed_only_when_asked():
    image = np.random.default_rng(0).integers(0, 256, size=(36, 48, 3), dtype=np.uint8)
    torch.manual_seed(0)
    relocalizer = Relocalizer(
        PoseNet(input_size=32, width=0.0625, feature_dim=16), ExhaustiveIndex(), SeedRecorder()
    )
    query = QueryWindows(image, relocalizer.scorer)
    told = query.search_query()  # what an ask/tell search is told of the query
    assert "query_seed" not in vars(query)  # a centre crop or sweep never pays the hash
    assert told.seed == image_fingerprint(image) == image_fingerprint(image.copy())
    assert query_seed(query) == told.seed  # the older form's distance carries the same
    assert image_fingerprint(image[:, ::-1]) != image_fingerprint(image)


class SeedRecorder(CropSearch):
    """The older, blocking form: reads the seed from its distance."""

    def __init__(self):
        self.seeds = []

    def search(self, width, height, distance):
        self.seeds.append(query_seed(distance))
        return crop_at(0, width, height)


class ProposalSeedRecorder(CropSearch):
    """The ask/tell form: reads the seed from its SearchQuery."""

    def __init__(self):
        self.seeds = []

    def propose(self, query):
        self.seeds.append(query.seed)
        return crop_at(0, query.width, query.height)
        yield  # a generator that asks for nothing


@pytest.mark.parametrize("form", [SeedRecorder, ProposalSeedRecorder], ids=["search", "propose"])
def test_the_pipeline_hands_each_image_its_fingerprint_as_query_seed(form):
    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.0625, feature_dim=16)
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, size=(36, 48, 3), dtype=np.uint8) for _ in range(3)]
    search = form()
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), search)
    relocalizer.fit(images)
    for image in [images[0], images[1], images[0].copy()]:
        relocalizer.localize(image)
    assert search.seeds[0] == search.seeds[2] == image_fingerprint(images[0])
    assert search.seeds[1] == image_fingerprint(images[1]) != search.seeds[0]


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
