"""The pipeline's test-time sampling: only the chosen crop is sampled, seeded per query."""

import numpy as np
import pytest
import torch

from relocfw import Crop, QueryOptions, Relocalizer
from relocfw.core.errors import ConfigError
from relocfw.core.imaging import Strip, image_fingerprint
from relocfw.core.sampling import combine_samples, query_streams, random_windows
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.retrieval_refiner import RetrievalRefiner


class SamplesSeen(PoseNet):
    """Records how many dropout samples each forward pass ran with, and its batch."""

    # Declared, so the pipeline does not measure it with passes of its own (which
    # would be among the calls recorded); tests/core/test_sampling_cost.py measures it.
    sample_share = 0.25

    def __init__(self, variant: str = "kendall", samples: int = 8, crop_scale: float = 1.5):
        torch.manual_seed(0)
        super().__init__(
            input_size=32, width=0.125, feature_dim=32, mc_samples=samples, dropout_variant=variant
        )
        self.set_crop_scale(crop_scale)
        self.calls: list[tuple[int, int]] = []

    def forward(self, images):
        self.calls.append((self.mc_samples, len(images)))
        return super().forward(images)


@pytest.fixture
def scene_images(tiny_scene):
    train = load_sevenscenes(tiny_scene, None, "train")
    test = load_sevenscenes(tiny_scene, None, "test")
    return read_images(train, quiet=True), read_images(test, quiet=True)


def test_the_map_and_the_candidates_are_scored_dropout_free_and_the_choice_sampled_once(
    scene_images,
):
    train, test = scene_images
    backbone = SamplesSeen()
    relocalizer = Relocalizer(backbone, KMeansIndex(k=4), GeneticCropSearch(seed=0))
    relocalizer.fit(train)
    assert {samples for samples, _ in backbone.calls} == {0}
    backbone.calls.clear()
    sampled = relocalizer.localize(test[0])
    # Every GA generation ran dropout-free; then one pass of the chosen crop, sampled.
    assert [c for c in backbone.calls if c[0] > 0] == [(8, 1)] == backbone.calls[-1:]
    assert backbone.mc_samples == 8  # restored after the dropout-free passes
    backbone.mc_samples = 0
    plain = relocalizer.localize(test[0])
    # Sampling cannot move the crop: the index saw the same descriptors.
    assert plain.crop == sampled.crop and plain.distance == sampled.distance
    assert not np.allclose(plain.pose.position, sampled.pose.position)
    assert sampled.position_spread > 0 and np.isnan(plain.position_spread)


def test_a_querys_samples_do_not_depend_on_what_ran_before(scene_images):
    train, test = scene_images
    relocalizer = Relocalizer(
        SamplesSeen(), ExhaustiveIndex(), CentreCrop(), QueryOptions(crop_samples=6)
    )
    relocalizer.fit(train)
    first = relocalizer.localize(test[1])
    torch.rand(100)  # the caller's stream moves on...
    relocalizer.localize(test[0])  # ...and another query is sampled in between
    again = relocalizer.localize(test[1])
    assert np.array_equal(first.pose.position, again.pose.position)
    assert first.position_spread == again.position_spread
    other_seed = Relocalizer(
        relocalizer.backbone,
        relocalizer.index,
        CentreCrop(),
        QueryOptions(crop_samples=6, sample_seed=1),
    ).localize(test[1])
    assert not np.array_equal(first.pose.position, other_seed.pose.position)


def test_sampling_leaves_the_callers_random_stream_alone(scene_images):
    train, test = scene_images
    relocalizer = Relocalizer(SamplesSeen(), ExhaustiveIndex(), CentreCrop())
    relocalizer.fit(train)
    torch.manual_seed(5)
    expected = torch.rand(3)
    torch.manual_seed(5)
    relocalizer.localize(test[0])
    assert torch.equal(torch.rand(3), expected)


def test_crop_sampling_alone_answers_with_the_mean_of_its_windows(scene_images):
    train, test = scene_images
    backbone = SamplesSeen(samples=0)
    relocalizer = Relocalizer(
        backbone, ExhaustiveIndex(), CentreCrop(), QueryOptions(crop_samples=5)
    )
    relocalizer.fit(train)
    backbone.calls.clear()
    answer = relocalizer.localize(test[2])
    # One dropout-free pass of the centre window, then the 5 random windows together.
    assert backbone.calls == [(0, 1), (0, 5)]
    assert answer.network_passes == 6
    # Recompute from the same windows: the seeded draw is reproducible.
    strip = Strip(test[2], 32, 1.5)
    windows_rng, _ = query_streams(0, image_fingerprint(test[2]))
    corners = random_windows(strip, answer.crop, 5, windows_rng)
    windows = relocalizer.scorer.forward(torch.stack([strip.cut(c) for c in corners]))
    position, _, spread, _ = combine_samples(windows.positions, windows.quaternions)
    assert np.allclose(answer.pose.position, position)
    assert answer.position_spread == pytest.approx(spread) and spread > 0


def test_crop_sampling_with_dropout_gives_each_window_one_mask(scene_images):
    train, test = scene_images
    backbone = SamplesSeen(samples=40)
    relocalizer = Relocalizer(
        backbone, ExhaustiveIndex(), CentreCrop(), QueryOptions(crop_samples=7)
    )
    relocalizer.fit(train)
    backbone.calls.clear()
    answer = relocalizer.localize(test[0])
    assert backbone.calls == [(0, 1), (1, 7)]
    # The centre window, then 7 windows that each rerun a quarter of the net once.
    assert answer.network_passes == pytest.approx(1 + 7 * (1 + 0.25))


def test_random_windows_stay_inside_the_chosen_crop():
    image = np.zeros((60, 100, 3), np.uint8)
    strip = Strip(image, 32, 1.5)  # short side 48: a crop's square is 48, its window 32
    crop = Crop(30, 0, 60)
    corners = random_windows(strip, crop, 500, np.random.default_rng(0))
    top, left = round(crop.y * strip.scale), round(crop.x * strip.scale)
    ys, xs = np.array(corners).T
    assert ys.min() == top and ys.max() == top + 16
    assert xs.min() == left and xs.max() == left + 16
    assert strip.window(crop) in set(corners)  # the centred window is one of the draws


def test_impossible_sampling_options_are_refused():
    with pytest.raises(ConfigError, match="crop_samples must be at least 0, got -1"):
        Relocalizer(SamplesSeen(), ExhaustiveIndex(), CentreCrop(), QueryOptions(crop_samples=-1))
    # refine=retrieval answers with map images' poses: sampling the network's is refused.
    with pytest.raises(ConfigError, match="backbone.mc_samples=8 sample that pose"):
        Relocalizer(SamplesSeen(), ExhaustiveIndex(), CentreCrop(), refiner=RetrievalRefiner())


def test_crop_sampling_is_refused_for_a_model_whose_window_fills_the_crop():
    with pytest.raises(ConfigError, match="the window fills the crop"):
        Relocalizer(
            SamplesSeen(crop_scale=1.0),
            ExhaustiveIndex(),
            CentreCrop(),
            QueryOptions(crop_samples=4),
        )
    with pytest.raises(ConfigError, match="sample_seed must be at least 0, got -1"):
        Relocalizer(SamplesSeen(), ExhaustiveIndex(), CentreCrop(), QueryOptions(sample_seed=-1))


def test_the_sampling_streams_are_not_the_crop_searchs():
    windows, torch_seed = query_streams(0, 12345)
    ga_stream = np.random.default_rng([0, 12345])  # what GeneticCropSearch(seed=0) draws
    assert not np.array_equal(windows.integers(0, 2**31, 8), ga_stream.integers(0, 2**31, 8))
    again, same_seed = query_streams(0, 12345)
    assert same_seed == torch_seed and torch_seed != query_streams(0, 12346)[1]
