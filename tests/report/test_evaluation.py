"""The headline numbers: summarise() on answers with known errors, and timed evaluation."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from relocfw.core.errors import ConfigError
from relocfw.core.query_options import QueryOptions
from relocfw.core.values import Crop, Localization, Pose
from relocfw.data.frames import Frame
from relocfw.report.evaluation import MethodResult, evaluate, evaluate_round_robin, summarise

IDENTITY = (1.0, 0.0, 0.0, 0.0)


def about_z(degrees: float) -> tuple[float, float, float, float]:
    half = np.radians(degrees) / 2
    return (np.cos(half), 0.0, 0.0, np.sin(half))


# Per query: position error (m, along x), orientation error (deg, about z), seconds,
# network passes, crops scored. Chosen so that medians and means differ.
ERRORS = [
    (0.1, 2.0, 0.010, 1.0, 1),
    (0.4, 14.0, 0.020, 12.5, 30),
    (0.6, 5.0, 0.030, 3.0, 3),  # too far
    (0.2, 20.0, 0.040, 2.0, 2),  # turned too much
    (3.0, 90.0, 0.500, 4.0, 4),  # an outlier in everything
]


def known_result() -> MethodResult:
    frames, answers = [], []
    for i, (metres, degrees, seconds, passes, crops) in enumerate(ERRORS):
        truth = Pose(np.array([1.0, 2.0, 3.0]), np.array(IDENTITY))
        frames.append(Frame(f"q{i}", Path(f"q{i}.png"), truth))
        estimate = Pose(truth.position + [metres, 0.0, 0.0], np.array(about_z(degrees)))
        answer = Localization(estimate, Crop(0, 0, 10), 0.5, crops, seconds, network_passes=passes)
        answers.append(answer)
    return MethodResult("known", tuple(frames), tuple(answers))


def test_summary_holds_medians_means_share_and_costs():
    summary = summarise(known_result())
    assert summary["method"] == "known" and summary["queries"] == 5
    assert summary["median_position_m"] == pytest.approx(0.4)
    assert summary["mean_position_m"] == pytest.approx(4.3 / 5)
    assert summary["median_orientation_deg"] == pytest.approx(14.0)
    assert summary["mean_orientation_deg"] == pytest.approx(131.0 / 5)
    # Within 0.5 m AND 15 deg: only the first two.
    assert summary["share_within_0.5m_15deg"] == pytest.approx(2 / 5)
    assert summary["median_seconds_per_query"] == pytest.approx(0.030)
    assert summary["mean_seconds_per_query"] == pytest.approx(0.600 / 5)
    assert summary["mean_network_passes"] == pytest.approx(22.5 / 5)
    assert summary["mean_crops_scored"] == pytest.approx(40 / 5)


def test_the_network_part_is_the_time_before_the_refiner():
    base = known_result()
    parts = [
        {"retrieval": 0.001, "features": 0.004, "matching": 0.002, "solve": 0.001},
        {"retrieval": 0.001, "features": 0.010, "matching": 0.004, "solve": 0.001},
        # A second match near the first answer (refine.rematch): likewise.
        {"retrieval": 0.002, "features": 0.012, "matching": 0.008, "solve": 0.002, "rematch": 0.01},
        # A lost track: the retry's parts are added into the others, and
        # tracking_retry (their sum) must not be counted a second time.
        {"retrieval": 0.002, "features": 0.020, "solve": 0.004, "tracking_retry": 0.010},
        {"retrieval": 0.001, "features": 0.400, "matching": 0.050, "solve": 0.010},
    ]
    answers = tuple(
        dataclasses.replace(a, refine_seconds=p) for a, p in zip(base.answers, parts, strict=True)
    )
    summary = summarise(MethodResult("refined", base.frames, answers))
    # Before the refiner: 0.002, 0.004, 0.006, 0.014, 0.039 s.
    assert summary["median_ms_network"] == pytest.approx(6.0)
    assert summarise(base)["median_ms_network"] == pytest.approx(30.0)  # no refiner


def test_the_thresholds_are_strict_inequalities():
    truth = Pose(np.zeros(3), np.array(IDENTITY))
    frames = (Frame("a", Path("a.png"), truth), Frame("b", Path("b.png"), truth))
    on_the_line = Pose(np.array([0.5, 0.0, 0.0]), np.array(IDENTITY))
    inside = Pose(np.array([0.499, 0.0, 0.0]), np.array(about_z(14.99)))
    answers = tuple(Localization(p, Crop(0, 0, 1), 0.0, 1, 0.0) for p in (on_the_line, inside))
    assert summarise(MethodResult("edge", frames, answers))["share_within_0.5m_15deg"] == 0.5


class CountingRelocalizer:
    """Answers with the identity pose; each answer's `evaluations` is its call number.

    `options` says how many queries go at once, as a Relocalizer's do.
    """

    def __init__(self, queries_at_once=1):
        self.seen = []
        self.groups = []
        self.options = QueryOptions(queries_at_once=queries_at_once)

    def localize(self, image):
        self.seen.append(int(image[0, 0, 0]))
        call = len(self.seen)
        return Localization(Pose(np.zeros(3), np.array(IDENTITY)), Crop(0, 0, 1), 0.0, call, 0.0)

    def localize_many(self, images, queries_at_once):
        self.groups.append([int(image[0, 0, 0]) for image in images])
        return [self.localize(image) for image in images]


def images_and_frames(count):
    images = [np.full((2, 3, 3), i, dtype=np.uint8) for i in range(count)]
    pose = Pose(np.zeros(3), np.array(IDENTITY))
    return [Frame(f"f{i}", Path(f"f{i}.png"), pose) for i in range(count)], images


def test_warm_up_localizes_the_first_image_once_more_and_keeps_it_out_of_the_answers():
    frames, images = images_and_frames(4)
    relocalizer = CountingRelocalizer()
    result = evaluate("m", relocalizer, frames, images, quiet=True, warm_up=True)
    assert relocalizer.seen == [0, 0, 1, 2, 3]
    # The answers are those of calls 2..5: the warm-up's answer (call 1) is dropped.
    assert [a.evaluations for a in result.answers] == [2, 3, 4, 5]
    assert result.frames == tuple(frames)


def test_without_warm_up_every_image_is_localized_once():
    frames, images = images_and_frames(3)
    relocalizer = CountingRelocalizer()
    result = evaluate("m", relocalizer, frames, images, quiet=True, warm_up=False)
    assert relocalizer.seen == [0, 1, 2]
    assert [a.evaluations for a in result.answers] == [1, 2, 3]


def test_a_split_is_localized_in_groups_of_queries_at_once_and_in_order():
    frames, images = images_and_frames(5)
    relocalizer = CountingRelocalizer(queries_at_once=2)
    result = evaluate("m", relocalizer, frames, images, quiet=True, warm_up=False)
    assert relocalizer.groups == [[0, 1], [2, 3], [4]]
    assert [a.evaluations for a in result.answers] == [1, 2, 3, 4, 5]


class LoggingRelocalizer(CountingRelocalizer):
    """A CountingRelocalizer that also writes (its name, image) into a shared log."""

    def __init__(self, name, log, queries_at_once=1):
        super().__init__(queries_at_once)
        self.name, self.log = name, log

    def localize(self, image):
        self.log.append((self.name, int(image[0, 0, 0])))
        return super().localize(image)


def test_round_robin_rotates_the_methods_and_answers_as_one_method_at_a_time():
    frames, images = images_and_frames(4)
    log = []
    methods = {name: LoggingRelocalizer(name, log) for name in ("a", "b", "c")}
    results = evaluate_round_robin(methods, frames, images, quiet=True)
    warm_up = [("a", 0), ("b", 0), ("c", 0)]
    turns = [("a", 0), ("b", 0), ("c", 0), ("b", 1), ("c", 1), ("a", 1)]
    turns += [("c", 2), ("a", 2), ("b", 2), ("a", 3), ("b", 3), ("c", 3)]
    assert log == warm_up + turns
    alone = evaluate("a", CountingRelocalizer(), frames, images, quiet=True)
    for name, result in results.items():
        assert result.method == name and result.frames == tuple(frames)
        assert [a.evaluations for a in result.answers] == [a.evaluations for a in alone.answers]


def test_round_robin_refuses_methods_that_answer_in_groups():
    frames, images = images_and_frames(2)
    methods = {"one": CountingRelocalizer(), "grouped": CountingRelocalizer(queries_at_once=4)}
    with pytest.raises(ConfigError, match="'grouped' answers 4 at once"):
        evaluate_round_robin(methods, frames, images, quiet=True)
