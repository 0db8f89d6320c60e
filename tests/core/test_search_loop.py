"""One loop drives a group's ask/tell searches: merged passes, no threads, errors in place."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from relocfw import ConfigError, Crop, CropSearch, QueryOptions, Relocalizer, RelocfwError
from relocfw.core.interfaces import SearchQuery, crop_at, crop_side_and_span, drive
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop


class CountingPoseNet(PoseNet):
    """A tiny seeded PoseNet that records the size of every forward pass."""

    def __init__(self) -> None:
        torch.manual_seed(0)
        super().__init__(input_size=32, width=0.125, feature_dim=32)
        self.batches: list[int] = []

    def forward(self, images):
        self.batches.append(len(images))
        return super().forward(images)


@pytest.fixture(scope="module")
def scene(tiny_scene):
    train = read_images(load_sevenscenes(tiny_scene, None, "train"), quiet=True)
    test = read_images(load_sevenscenes(tiny_scene, None, "test"), quiet=True)
    return train, test


def fitted(train, search, **options) -> Relocalizer:
    relocalizer = Relocalizer(
        CountingPoseNet(), ExhaustiveIndex(), search, QueryOptions(batch_size=512, **options)
    )
    relocalizer.fit(train)
    relocalizer.backbone.batches.clear()
    return relocalizer


class OldStyleSweep(CropSearch):
    """A third-party search written against the older blocking form only."""

    def search(self, width, height, distance):
        _, span = crop_side_and_span(width, height)
        crops = [crop_at(o, width, height) for o in range(span + 1)]
        return crops[int(np.argmin(distance(crops)))]


def test_a_search_in_the_older_form_runs_one_query_at_a_time_with_the_same_answers(scene):
    train, test = scene
    old = fitted(train, OldStyleSweep())
    new = fitted(train, SweepCrop())
    many = old.localize_many(test, queries_at_once=len(test))
    assert [a.crop for a in many] == [a.crop for a in new.localize_many(test)]
    # One query at a time: one pass per query, never a merged one.
    assert len(old.backbone.batches) == len(test)


def test_a_group_runs_one_merged_forward_pass_per_round(scene):
    train, test = scene
    relocalizer = fitted(train, GeneticCropSearch(population=6, iterations=2, seed=0))
    many = relocalizer.localize_many(test, queries_at_once=len(test))
    # At most one pass per GA generation (3) plus the chosen windows (already scored):
    # every round merges all queries' new windows.
    assert len(relocalizer.backbone.batches) <= 3
    assert sum(relocalizer.backbone.batches) == sum(a.evaluations for a in many)


def test_localize_many_starts_no_thread(scene, monkeypatch):
    train, test = scene
    relocalizer = fitted(train, GeneticCropSearch(seed=0))
    before = threading.active_count()

    def refuse(self):
        raise AssertionError("the pipeline started a thread")

    monkeypatch.setattr(threading.Thread, "start", refuse)
    relocalizer.localize_many(test, queries_at_once=4)
    assert threading.active_count() == before


class FailsOnSecondQuery(CropSearch):
    def __init__(self, error: BaseException) -> None:
        self.error = error
        self.started = 0

    def propose(self, query):
        self.started += 1
        if self.started == 2:
            raise self.error
        distances = yield [crop_at(0, query.width, query.height)]
        assert len(distances) == 1
        return crop_at(0, query.width, query.height)


@pytest.mark.parametrize("error", [ValueError("on purpose"), KeyboardInterrupt()])
def test_an_error_in_one_search_is_raised_where_it_happens(scene, error):
    train, test = scene
    relocalizer = fitted(train, FailsOnSecondQuery(error))
    with pytest.raises(type(error)):
        relocalizer.localize_many(test, queries_at_once=4)
    # Raised while the searches were being started: no network pass ran after it.
    assert relocalizer.backbone.batches == []


class ChoosesNothing(CropSearch):
    def propose(self, query):
        yield [crop_at(0, query.width, query.height)]
        return None


class ChoosesOutside(CropSearch):
    def propose(self, query):
        return Crop(query.width, 0, min(query.width, query.height))
        yield


@pytest.mark.parametrize("search", [ChoosesNothing(), ChoosesOutside()], ids=type)
def test_a_choice_that_is_not_a_crop_of_the_image_is_one_clear_error(scene, search):
    train, test = scene
    relocalizer = fitted(train, search)
    with pytest.raises(RelocfwError, match=type(search).__name__):
        relocalizer.localize(test[0])


def test_a_search_must_define_propose_or_search():
    class Neither(CropSearch):
        pass

    with pytest.raises(TypeError, match="defines propose"):
        Neither()


def test_search_derived_from_propose_drives_the_same_generator():
    distances = {o: abs(o - 7) + 0.5 for o in range(41)}

    def distance(crops):
        return np.array([distances[c.x] for c in crops])

    ga = GeneticCropSearch(population=8, iterations=4, seed=1)
    by_search = ga.search(60, 20, distance)
    by_drive = drive(ga.propose(SearchQuery(60, 20)), distance)
    assert by_search == by_drive and by_search.size == 20
    assert SweepCrop().search(60, 20, distance) == Crop(7, 0, 20)
    assert CentreCrop().search(60, 20, distance) == Crop(20, 0, 20)


def test_the_query_seed_is_read_only_by_searches_that_draw_random_numbers():
    calls = []

    def seed_of():
        calls.append(1)
        return 5

    for search in (CentreCrop(), SweepCrop()):
        drive(search.propose(SearchQuery(60, 20, seed_of)), lambda c: np.zeros(len(c)))
    assert calls == []
    query = SearchQuery(60, 20, seed_of)
    drive(GeneticCropSearch().propose(query), lambda c: np.zeros(len(c)))
    assert calls == [1] and query.seed == 5


def test_options_are_one_checked_value():
    with pytest.raises(ConfigError, match="batch_size must be at least 1"):
        QueryOptions(batch_size=0)
    with pytest.raises(ConfigError, match="scoring must be one of plain, shared"):
        QueryOptions(scoring="fancy")
    with pytest.raises(ConfigError, match="rerank=3 re-scores"):
        QueryOptions(rerank=3)
    with pytest.raises(ConfigError, match="query: unknown option"):
        QueryOptions.from_mapping({"batchsize": 3})
    options = QueryOptions.from_mapping({"batch_size": 4.0, "scoring": None})
    assert options.batch_size == 4 and isinstance(options.batch_size, int)
    assert options.replace(scoring="shared", rerank=2, crop_samples=None).rerank == 2
