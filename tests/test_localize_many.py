"""Batched evaluation: many queries' windows in shared passes, the same answers."""

import threading

import numpy as np
import pytest
import torch

from relocfw import ConfigError, Relocalizer
from relocfw.core.interfaces import CropSearch, crop_at
from relocfw.core.lockstep import Lockstep
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
    relocalizer = Relocalizer(backbone, KMeansIndex(k=4), crop, scoring=scoring, batch_size=256)
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
        backbone, ExhaustiveIndex(), GeneticCropSearch(seed=1), crop_samples=4
    )
    relocalizer.fit(train)
    single = [relocalizer.localize(image) for image in test]
    many = relocalizer.localize_many(test, queries_at_once=3)  # groups of 3, 3, ...
    assert_same(many, single)
    assert [a.position_spread for a in many] == pytest.approx([a.position_spread for a in single])


class Failing(CropSearch):
    def search(self, width, height, distance):
        distance([crop_at(0, width, height)])
        raise ValueError("search failed on purpose")


def test_a_failing_search_fails_the_call_and_leaves_no_thread_behind(scene):
    train, test = scene
    relocalizer = Relocalizer(BatchRecorder(), ExhaustiveIndex(), Failing())
    relocalizer.fit(train)
    before = threading.active_count()
    with pytest.raises(ValueError, match="on purpose"):
        relocalizer.localize_many(test, queries_at_once=4)
    assert threading.active_count() == before


def test_impossible_group_size_is_refused(scene):
    relocalizer = Relocalizer(BatchRecorder(), ExhaustiveIndex(), CentreCrop())
    with pytest.raises(ConfigError, match="queries_at_once must be an integer >= 1"):
        relocalizer.localize_many(scene[1], queries_at_once=0)
    with pytest.raises(ConfigError, match="queries_at_once must be an integer >= 1"):
        Relocalizer(BatchRecorder(), ExhaustiveIndex(), CentreCrop(), queries_at_once=2.5)


def test_lockstep_waits_for_every_running_member_then_answers_all_at_once():
    merged = []

    def together(requests):
        merged.append(sorted(requests))
        return [r * 10 for r in requests]

    lockstep = Lockstep(3, together)
    results = {}

    def member(m, asks):
        for value in asks:
            results.setdefault(m, []).append(lockstep.ask(m, value))
        lockstep.leave(m)

    threads = [
        threading.Thread(target=member, args=(0, [1, 2])),
        threading.Thread(target=member, args=(1, [3])),
        threading.Thread(target=member, args=(2, [4, 5])),
    ]
    for thread in threads:
        thread.start()
    lockstep.serve()  # returns once every member has left
    for thread in threads:
        thread.join()
    assert results == {0: [10, 20], 1: [30], 2: [40, 50]}
    # Round one has all three; member 1 then leaves and round two has the other two.
    assert merged == [[1, 3, 4], [2, 5]] and lockstep.calls == 2


def test_lockstep_runs_every_call_on_the_serving_thread_and_hands_errors_back():
    ran_on = []

    def together(requests):
        ran_on.append(threading.get_ident())
        return [r + 1 for r in requests]

    def solo(value):
        ran_on.append(threading.get_ident())
        if value < 0:
            raise ValueError("negative")
        return value * 2

    lockstep = Lockstep(2, together)
    results, errors = {}, {}

    def member(m, value):
        try:
            doubled = lockstep.call(m, lambda: solo(value))
            results[m] = lockstep.ask(m, doubled)
        except ValueError as error:
            errors[m] = str(error)
        finally:
            lockstep.leave(m)

    threads = [threading.Thread(target=member, args=(m, v)) for m, v in ((0, 3), (1, -1))]
    for thread in threads:
        thread.start()
    lockstep.serve()
    for thread in threads:
        thread.join()
    assert results == {0: 7} and errors == {1: "negative"}
    assert set(ran_on) == {threading.get_ident()} and len(ran_on) == 3


def test_batched_seconds_include_sampling_and_leave_the_backbone_and_rng_alone(scene, monkeypatch):
    import time

    train, test = scene
    backbone = BatchRecorder(mc_samples=4)
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), CentreCrop())
    relocalizer.fit(train)
    sampled = relocalizer._sampled_answer

    def slow(*args):
        time.sleep(0.05)
        return sampled(*args)

    monkeypatch.setattr(relocalizer, "_sampled_answer", slow)
    torch.manual_seed(9)
    expected = torch.rand(2)
    torch.manual_seed(9)
    answers = relocalizer.localize_many(test[:4], queries_at_once=4)
    # The group's time, sampling included, shared among its 4 queries.
    assert all(a.seconds >= 0.05 for a in answers)
    assert backbone.mc_samples == 4 and torch.equal(torch.rand(2), expected)
