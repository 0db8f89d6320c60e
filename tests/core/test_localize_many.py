"""Batched evaluation: many queries' windows in shared passes, the same answers."""

import threading

import numpy as np
import pytest
import torch

from relocfw import ConfigError, QueryOptions, Relocalizer
from relocfw.core.interfaces import CropSearch, crop_at
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop


class BatchRecorder(PoseNet):
    def __init__(self, **options):
        torch.manual_seed(0)
        super().__init__(input_size=32, width=0.125, feature_dim=32, **options)
        self.batches: list[int] = []

    def forward(self, images):
        self.batches.append(len(images))
        return super().forward(images)


@pytest.fixture(scope="module")
def scene(tiny_scene):
    train = read_images(load_sevenscenes(tiny_scene, None, "train"), quiet=True)
    test = read_images(load_sevenscenes(tiny_scene, None, "test"), quiet=True)
    return train, test


def assert_same(many, single):
    assert len(many) == len(single)
    for a, b in zip(many, single, strict=True):
        assert a.crop == b.crop
        assert a.distance == pytest.approx(b.distance, rel=1e-5, abs=1e-6)
        assert np.allclose(a.pose.position, b.pose.position, atol=1e-5)
        assert np.allclose(a.pose.quaternion, b.pose.quaternion, atol=1e-5)
        assert a.evaluations == b.evaluations


@pytest.mark.parametrize(
    "crop, scoring",
    [
        (CentreCrop(), "plain"),
        (GeneticCropSearch(seed=0), "plain"),
        (SweepCrop(), "plain"),
        (GeneticCropSearch(seed=0), "shared"),
    ],
    ids=["centre", "ga", "sweep", "ga-shared"],
)
def test_batched_answers_equal_one_at_a_time(scene, crop, scoring):
    train, test = scene
    backbone = BatchRecorder()
    options = QueryOptions(scoring=scoring, batch_size=256)
    relocalizer = Relocalizer(backbone, KMeansIndex(k=4), crop, options)
    relocalizer.fit(train)
    backbone.batches.clear()
    single = [relocalizer.localize(image) for image in test]
    one_at_a_time = len(backbone.batches)
    backbone.batches.clear()
    many = relocalizer.localize_many(test, queries_at_once=len(test))
    assert_same(many, single)
    # Fewer, larger passes: the centre crops of all queries in one.
    assert len(backbone.batches) < one_at_a_time
    if isinstance(crop, CentreCrop):
        assert backbone.batches == [len(test)]


def test_groups_and_sampling_match_one_at_a_time(scene):
    train, test = scene
    backbone = BatchRecorder(mc_samples=6, dropout_variant="kendall")
    backbone.set_crop_scale(1.5)
    relocalizer = Relocalizer(
        backbone, ExhaustiveIndex(), GeneticCropSearch(seed=1), QueryOptions(crop_samples=4)
    )
    relocalizer.fit(train)
    single = [relocalizer.localize(image) for image in test]
    many = relocalizer.localize_many(test, queries_at_once=3)  # groups of 3, 3, ...
    assert_same(many, single)
    assert [a.position_spread for a in many] == pytest.approx([a.position_spread for a in single])


class Failing(CropSearch):
    """The older, blocking form: its queries run one at a time."""

    def search(self, width, height, distance):
        distance([crop_at(0, width, height)])
        raise ValueError("search failed on purpose")


class FailingProposals(CropSearch):
    """The ask/tell form: fails after its first round, inside the group's loop."""

    def propose(self, query):
        yield [crop_at(0, query.width, query.height)]
        raise ValueError("search failed on purpose")


@pytest.mark.parametrize("search", [Failing, FailingProposals], ids=["search", "propose"])
def test_a_failing_search_fails_the_call_and_leaves_no_thread_behind(scene, search):
    train, test = scene
    relocalizer = Relocalizer(BatchRecorder(), ExhaustiveIndex(), search())
    relocalizer.fit(train)
    before = threading.active_count()
    with pytest.raises(ValueError, match="on purpose"):
        relocalizer.localize_many(test, queries_at_once=4)
    assert threading.active_count() == before


def test_impossible_group_size_is_refused(scene):
    relocalizer = Relocalizer(BatchRecorder(), ExhaustiveIndex(), CentreCrop())
    with pytest.raises(ConfigError, match="queries_at_once must be at least 1, got 0"):
        relocalizer.localize_many(scene[1], queries_at_once=0)
    with pytest.raises(ConfigError, match="queries_at_once must be an integer, got 2.5"):
        Relocalizer(
            BatchRecorder(), ExhaustiveIndex(), CentreCrop(), QueryOptions(queries_at_once=2.5)
        )


def test_batched_seconds_include_sampling_and_leave_the_backbone_and_rng_alone(scene, monkeypatch):
    import time

    from relocfw.core import pipeline

    train, test = scene
    backbone = BatchRecorder(mc_samples=4)
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), CentreCrop())
    relocalizer.fit(train)
    sampled = pipeline.sampled_answer  # what Relocalizer.answer samples the chosen crop with

    def slow(*args):
        time.sleep(0.05)
        return sampled(*args)

    monkeypatch.setattr(pipeline, "sampled_answer", slow)
    torch.manual_seed(9)
    expected = torch.rand(2)
    torch.manual_seed(9)
    answers = relocalizer.localize_many(test[:4], queries_at_once=4)
    # The group's time, sampling included, shared among its 4 queries.
    assert all(a.seconds >= 0.05 for a in answers)
    assert backbone.mc_samples == 4 and torch.equal(torch.rand(2), expected)
