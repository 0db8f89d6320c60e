"""scoring=scout: candidate windows ranked by the backbone's cheaper copy, the chosen
crop answered by the plain network (the int8 graph of engine=onnx is such a copy:
tests/model/test_onnx_engine.py)."""

import numpy as np
import pytest
import torch

from relocfw import ConfigError, QueryOptions, Relocalizer
from relocfw.core.imaging import Strip
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop


def tiny_posenet() -> PoseNet:
    torch.manual_seed(0)
    return PoseNet(input_size=32, width=0.125, feature_dim=32)


class NoisyScout(PoseNet):
    """A scout that ranks differently from the network: its descriptors plus noise
    fixed by each window's pixels (as an int8 copy's rounding is)."""

    def scout_features(self, images):
        features = self(images).features
        seeds = (images.sum(dim=(1, 2, 3)) * 1000).long().tolist()
        noise = [
            torch.randn(features.shape[1], generator=torch.Generator().manual_seed(s))
            for s in seeds
        ]
        return features + 0.5 * features.std() * torch.stack(noise)


def noisy_scout() -> NoisyScout:
    torch.manual_seed(0)
    return NoisyScout(input_size=32, width=0.125, feature_dim=32)


@pytest.fixture
def scene(tiny_scene):
    from relocfw.data.frames import read_images
    from relocfw.data.sevenscenes import load_sevenscenes

    return tuple(
        read_images(load_sevenscenes(tiny_scene, None, split), quiet=True)
        for split in ("train", "test")
    )


def fitted(backbone, search, scene, **options) -> Relocalizer:
    relocalizer = Relocalizer(backbone, KMeansIndex(k=4), search, QueryOptions(**options))
    relocalizer.fit(scene[0])
    return relocalizer


def plain_answer(relocalizer: Relocalizer, image, crop):
    strip = Strip(image, 32)
    return relocalizer.scorer.forward(strip.cut(strip.window(crop))[None])


def recorded_plain_batches(relocalizer: Relocalizer, monkeypatch) -> list[list]:
    """The window corners of every plain batch the relocalizer's scorer runs from now."""
    batches = []
    plain = relocalizer.scorer.plain

    def recording(strip, corners):
        batches.append(list(corners))
        return plain(strip, corners)

    monkeypatch.setattr(relocalizer.scorer, "plain", recording)
    return batches


def test_without_a_cheaper_copy_the_scout_chooses_what_plain_scoring_does(scene):
    plain = fitted(tiny_posenet(), GeneticCropSearch(seed=0), scene)
    scout = fitted(tiny_posenet(), GeneticCropSearch(seed=0), scene, scoring="scout")
    for image in scene[1]:
        want, got = plain.localize(image), scout.localize(image)
        assert got.crop == want.crop
        assert got.evaluations == want.evaluations
        assert got.distance == pytest.approx(want.distance)
        np.testing.assert_allclose(got.pose.position, want.pose.position, atol=1e-6)
        # Every candidate by the scout, then the chosen crop once more by the network.
        assert got.network_passes == want.evaluations + 1


def test_the_scout_ranks_and_the_network_answers_the_chosen_crop(scene, monkeypatch):
    relocalizer = fitted(noisy_scout(), GeneticCropSearch(seed=0), scene, scoring="scout")
    batches = recorded_plain_batches(relocalizer, monkeypatch)
    image = scene[1][0]
    answer = relocalizer.localize(image)
    strip = Strip(image, 32)
    assert batches == [[strip.window(answer.crop)]]  # the chosen crop alone
    exact = plain_answer(relocalizer, image, answer.crop)
    np.testing.assert_allclose(answer.pose.position, exact.positions[0], atol=1e-6)
    np.testing.assert_allclose(answer.pose.quaternion, exact.quaternions[0], atol=1e-6)
    # The distance reported is the network's, not the scout's.
    assert answer.distance == pytest.approx(relocalizer.scorer.map_distance(exact.features)[0])


def test_a_noisy_scout_moves_choices_and_re_scoring_every_window_undoes_it(scene):
    plain = fitted(tiny_posenet(), SweepCrop(), scene)
    once = fitted(noisy_scout(), SweepCrop(), scene, scoring="scout")
    everything = fitted(noisy_scout(), SweepCrop(), scene, scoring="scout", rerank=1000)
    moved = 0
    for image in scene[1]:
        exact, reranked = plain.localize(image), everything.localize(image)
        strip = Strip(image, 32)
        assert strip.window(reranked.crop) == strip.window(exact.crop)
        assert reranked.distance == pytest.approx(exact.distance)
        np.testing.assert_allclose(reranked.pose.position, exact.pose.position, atol=1e-6)
        moved += strip.window(once.localize(image).crop) != strip.window(exact.crop)
    # The scout alone picks other windows on some images: otherwise the test would
    # pass whatever re-scoring did.
    assert moved > 0


def test_re_scoring_runs_the_best_scouted_windows_in_one_plain_batch(scene, monkeypatch):
    relocalizer = fitted(noisy_scout(), GeneticCropSearch(seed=0), scene, scoring="scout", rerank=3)
    batches = recorded_plain_batches(relocalizer, monkeypatch)
    image = scene[1][0]
    query_windows = []
    original = relocalizer.answer

    def keep(query, crop, **kwargs):
        query_windows.append((query, crop))
        return original(query, crop, **kwargs)

    monkeypatch.setattr(relocalizer, "answer", keep)
    answer = relocalizer.localize(image)
    ((query, searched),) = query_windows
    (batch,) = batches
    ranked = sorted(query.ranking, key=query.ranking.__getitem__)
    # The search's choice first, then the best scouted windows, three in all.
    assert batch == list(dict.fromkeys([query.strip.window(searched), *ranked]))[:3]
    assert query.strip.window(answer.crop) == min(batch, key=lambda c: query.plain[c][0])
    assert answer.network_passes == len(query.ranking) + 3


def test_queries_searched_together_answer_as_one_at_a_time(scene, monkeypatch):
    relocalizer = fitted(noisy_scout(), GeneticCropSearch(seed=0), scene, scoring="scout")
    alone = [relocalizer.localize(image) for image in scene[1]]
    calls = []
    scout = relocalizer.scorer.scout_together

    def recording(requests):
        calls.append(len(requests))
        return scout(requests)

    monkeypatch.setattr(relocalizer.scorer, "scout_together", recording)
    together = relocalizer.localize_many(scene[1], queries_at_once=len(scene[1]))
    for got, want in zip(together, alone, strict=True):
        assert got.crop == want.crop
        np.testing.assert_allclose(got.pose.position, want.pose.position, atol=1e-6)
    assert calls[0] == len(scene[1])  # the first round: every query's windows at once


def test_scout_options_are_checked():
    options = QueryOptions(scoring="scout", rerank=2)
    assert options.rerank == 2
    with pytest.raises(ConfigError, match="scoring must be one of plain, shared, scout"):
        QueryOptions(scoring="int8")
    with pytest.raises(ConfigError, match="use scoring=shared or scoring=scout"):
        QueryOptions(scoring="plain", rerank=2)
