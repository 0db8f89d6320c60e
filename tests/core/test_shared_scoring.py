"""scoring=shared: every candidate window pooled from one trunk pass over the strip."""

import numpy as np
import pytest
import torch

from relocfw import ConfigError, QueryOptions, Relocalizer
from relocfw.core.imaging import Strip
from relocfw.core.interfaces import Backbone
from relocfw.core.values import PoseOutput
from relocfw.core.window_pooling import StripMaps, coverage_weights
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop
from tests.core.test_scout_scoring import recorded_plain_batches


def tiny_posenet() -> PoseNet:
    torch.manual_seed(0)
    return PoseNet(input_size=32, width=0.125, feature_dim=32)


class BoxFilter(Backbone):
    """Maps = 8x8 block means: a window at a multiple of 8 pixels is exactly its cells."""

    input_size = 32
    feature_dim = 3

    def forward(self, images):
        pooled = images.mean(dim=(2, 3))
        return PoseOutput(pooled, torch.nn.functional.normalize(images[:, 0, :4, 0]), pooled)

    def feature_maps(self, images):
        return torch.nn.functional.avg_pool2d(images, 8)

    def describe_pooled(self, pooled):
        return pooled


def test_coverage_weights_split_the_end_cells():
    weights = coverage_weights(torch.tensor([0.5, 0.0, 2.0]), 2, 4)
    expected = [[0.25, 0.5, 0.25, 0.0], [0.5, 0.5, 0.0, 0.0], [0.0, 0.0, 0.5, 0.5]]
    assert torch.allclose(weights, torch.tensor(expected))


@pytest.mark.parametrize("shape", [(32, 56), (56, 32)])
def test_windows_on_the_cell_grid_pool_exactly(shape):
    height, width = shape
    torch.manual_seed(0)
    strip = torch.rand(1, 3, height, width)
    backbone = BoxFilter()
    maps = StripMaps(backbone.feature_maps(strip)[0], height, width, 32)
    corners = [(0, x) if width > height else (x, 0) for x in (0, 8, 16, 24)]
    pooled = maps.pooled(corners)
    for (y, x), row in zip(corners, pooled, strict=True):
        window = strip[:, :, y : y + 32, x : x + 32]
        assert torch.allclose(row, window.mean(dim=(0, 2, 3)), atol=1e-6)
    # Off the grid, the window is interpolated between its neighbours on the grid.
    between = maps.pooled([(0, 4)] if width > height else [(4, 0)])[0]
    assert torch.allclose(between, (pooled[0] + pooled[1]) / 2, atol=1e-6)


def test_a_square_image_gives_the_plain_descriptor():
    backbone = tiny_posenet().eval()
    image = torch.rand(1, 3, 32, 32)
    with torch.inference_mode():
        maps = StripMaps(backbone.feature_maps(image)[0], 32, 32, 32)
        shared = backbone.describe_pooled(maps.pooled([(0, 0)]))
        plain = backbone(image).features
    assert torch.allclose(shared, plain, atol=1e-5)


def fitted(scoring: str, crop, scene) -> Relocalizer:
    train, _ = scene
    relocalizer = Relocalizer(tiny_posenet(), KMeansIndex(k=4), crop, QueryOptions(scoring=scoring))
    relocalizer.fit(train)
    return relocalizer


@pytest.fixture
def scene(tiny_scene):
    from relocfw.data.frames import read_images
    from relocfw.data.sevenscenes import load_sevenscenes

    return tuple(
        read_images(load_sevenscenes(tiny_scene, None, split), quiet=True)
        for split in ("train", "test")
    )


def test_shared_ga_answers_with_the_plain_pose_of_its_crop(scene):
    shared = fitted("shared", GeneticCropSearch(seed=0), scene)
    plain = fitted("plain", CentreCrop(), scene)
    image = scene[1][0]
    answer = shared.localize(image)
    strip = Strip(image, 32)
    exact = plain.scorer.forward(strip.cut(strip.window(answer.crop))[None])
    assert np.allclose(answer.pose.position, exact.positions[0], atol=1e-6)
    assert np.allclose(answer.pose.quaternion, exact.quaternions[0], atol=1e-6)
    # One trunk pass over the 43x32 strip plus the chosen crop's plain pass.
    assert answer.network_passes == pytest.approx(1 + 43 * 32 / 32**2)
    assert 1 < answer.evaluations <= 12


def test_centre_crop_never_runs_the_strip(scene):
    answer = fitted("shared", CentreCrop(), scene).localize(scene[1][0])
    assert answer.network_passes == 1 and answer.evaluations == 1


def test_unknown_scoring_and_backbones_without_the_hooks_are_refused():
    with pytest.raises(ConfigError, match="scoring must be one of plain, shared"):
        Relocalizer(tiny_posenet(), KMeansIndex(k=4), CentreCrop(), QueryOptions(scoring="fast"))

    class PlainOnly(BoxFilter):
        feature_maps = Backbone.feature_maps

    with pytest.raises(ConfigError, match="PlainOnly lacks them"):
        Relocalizer(PlainOnly(), KMeansIndex(k=4), CentreCrop(), QueryOptions(scoring="shared"))


def test_a_window_inside_both_axes_pools_exactly_its_cells():
    # crop_scale > 1: windows move along both axes. Maps of 4 x 6 cells for a
    # 128 x 192 strip, 64-pixel windows of 2 x 2 cells: a window at a cell boundary
    # averages exactly its four cells.
    maps = torch.arange(3 * 4 * 6, dtype=torch.float64).reshape(3, 4, 6) ** 1.5
    strip = StripMaps(maps, 128, 192, 64, window_cells=2)
    pooled = strip.pooled([(32, 64), (0, 0), (64, 128)])
    for row, (y, x) in enumerate([(1, 2), (0, 0), (2, 4)]):
        expected = maps[:, y : y + 2, x : x + 2].mean(dim=(1, 2))
        assert torch.allclose(pooled[row], expected)


def test_without_window_cells_a_window_spans_the_short_side_as_before():
    maps = torch.rand(5, 3, 7, dtype=torch.float64)
    strip = StripMaps(maps, 96, 224, 96)
    pooled = strip.pooled([(0, 0), (0, 128)])
    assert torch.allclose(pooled[0], maps[:, :, :3].mean(dim=(1, 2)))
    assert torch.allclose(pooled[1], maps[:, :, 4:7].mean(dim=(1, 2)))


def test_shared_ga_with_a_crop_scale_answers_with_the_plain_pose_of_its_crop(scene):
    train, test = scene
    backbones = [tiny_posenet(), tiny_posenet()]
    for backbone in backbones:
        backbone.set_crop_scale(256 / 224)  # as training with train.crop_scale does
    shared = Relocalizer(
        backbones[0], KMeansIndex(k=4), GeneticCropSearch(seed=0), QueryOptions(scoring="shared")
    )
    shared.fit(train)
    plain = Relocalizer(backbones[1], KMeansIndex(k=4), CentreCrop())
    answer = shared.localize(test[0])
    strip = Strip(test[0], 32, 256 / 224)
    exact = plain.scorer.forward(strip.cut(strip.window(answer.crop))[None])
    assert np.allclose(answer.pose.position, exact.positions[0], atol=1e-6)
    assert np.allclose(answer.pose.quaternion, exact.quaternions[0], atol=1e-6)
    assert shared.scorer.window_cells() == 1  # a 32-pixel input gives 1 x 1 maps


def fitted_with(scoring: str, crop, scene, **options) -> Relocalizer:
    """Fitted with the same backbone weights as `fitted` (tiny_posenet is seeded)."""
    options = QueryOptions(scoring=scoring, **options)
    relocalizer = Relocalizer(tiny_posenet(), KMeansIndex(k=4), crop, options)
    relocalizer.fit(scene[0])
    return relocalizer


def test_re_scoring_every_window_makes_the_shared_sweep_the_plain_sweep(scene):
    plain = fitted_with("plain", SweepCrop(), scene)
    everything = fitted_with("shared", SweepCrop(), scene, rerank=1000)
    once = fitted_with("shared", SweepCrop(), scene, rerank=1)
    moved = 0
    for image in scene[1]:
        exact, reranked = plain.localize(image), everything.localize(image)
        strip = Strip(image, 32)
        assert strip.window(reranked.crop) == strip.window(exact.crop)
        assert reranked.distance == pytest.approx(exact.distance)
        assert np.allclose(reranked.pose.position, exact.pose.position)
        moved += strip.window(once.localize(image).crop) != strip.window(exact.crop)
    # Without re-scoring, the shared ranking alone picks other windows on some images:
    # the test would pass vacuously if the two rankings agreed everywhere.
    assert moved > 0


def test_re_scoring_runs_the_best_shared_windows_in_one_plain_batch(scene):
    backbone = tiny_posenet()
    relocalizer = Relocalizer(
        backbone,
        KMeansIndex(k=4),
        GeneticCropSearch(seed=0),
        QueryOptions(scoring="shared", rerank=3),
    )
    relocalizer.fit(scene[0])
    answer = relocalizer.localize(scene[1][0])
    # The strip pass, then 3 plain windows together; the chosen one is among them.
    assert answer.network_passes == pytest.approx(3 + 43 * 32 / 32**2)


@pytest.mark.parametrize(
    "scoring, rerank, message",
    [
        ("plain", 2, "with scoring=plain every candidate is already plain"),
        ("shared", 0, "rerank must be at least 1, got 0"),
    ],
)
def test_impossible_rerank_options_are_refused(scoring, rerank, message):
    with pytest.raises(ConfigError, match=message):
        Relocalizer(
            tiny_posenet(),
            KMeansIndex(k=4),
            CentreCrop(),
            QueryOptions(scoring=scoring, rerank=rerank),
        )


class RecordingGA(GeneticCropSearch):
    """The GA, remembering the crop it returned."""

    def propose(self, query):
        self.returned = yield from super().propose(query)
        return self.returned


def test_re_scoring_keeps_the_searchs_choice_among_the_candidates(scene, monkeypatch):
    search = RecordingGA(seed=0)
    options = QueryOptions(scoring="shared", rerank=3)
    relocalizer = Relocalizer(tiny_posenet(), KMeansIndex(k=4), search, options)
    relocalizer.fit(scene[0])
    plain_batches = recorded_plain_batches(relocalizer, monkeypatch)
    image = scene[1][0]
    answer = relocalizer.localize(image)
    strip = Strip(image, 32)
    # One plain batch of 3 windows, the search's own choice first among them.
    assert len(plain_batches) == 1 and len(plain_batches[0]) == 3
    assert plain_batches[0][0] == strip.window(search.returned)
    assert strip.window(answer.crop) in plain_batches[0]
