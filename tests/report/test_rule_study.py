"""The window recording file and the selection-rule study, on constructed queries."""

import numpy as np
import pytest

from relocfw.core.errors import DataError
from relocfw.core.values import Pose
from relocfw.core.window_rules import LearnedSelector, Windows
from relocfw.report import rule_study
from relocfw.report.diagnosis import QueryWindows
from relocfw.report.rule_study import (
    GATE_QUANTILES,
    ORACLE,
    REFERENCE,
    TEMPERATURES,
    as_markdown,
    choose_settings,
    fitted_selector,
    headroom_figure,
    rules_of,
    study,
)
from relocfw.report.window_recording import RecordedQuery, load_windows, save_windows
from tests.rotations import multiply

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
TRUTH = Pose([1.0, -2.0, 0.5], IDENTITY)


def turned(degrees, axis=(0.0, 0.0, 1.0)):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    half = np.radians(degrees) / 2
    return np.array([np.cos(half), *(np.sin(half) * axis)])


# --- the recording file ---------------------------------------------------------------


def diagnosed(frame, seed, views, centre, neighbours=True):
    """A QueryWindows as task=diagnose records it: offsets whose view is the same
    window share its distance and pose, as the network saw one input for them."""
    rng = np.random.default_rng(seed)
    views = np.asarray(views, dtype=float)
    _, window_of = np.unique(views, axis=0, return_inverse=True)
    distinct = window_of.max() + 1
    distances = rng.uniform(0.5, 2.0, distinct)[window_of]
    positions = rng.normal(size=(distinct, 3))[window_of]
    quaternions = np.array([turned(a, rng.normal(size=3)) for a in rng.uniform(0, 90, distinct)])
    quaternions = quaternions[window_of]
    n = len(views)
    return QueryWindows(
        frame=frame,
        crops=np.zeros((n, 3), dtype=np.int64),
        views=views,
        distances=distances,
        position_errors=np.zeros(n),
        orientation_errors=np.zeros(n),
        centre=centre,
        windows=int(distinct),
        positions=positions,
        quaternions=quaternions,
        neighbours=rng.integers(0, 6, size=(distinct, 3))[window_of] if neighbours else None,
        distance_scale=0.75,
        truth=Pose(rng.normal(size=3), turned(rng.uniform(0, 90))),
    )


MAP_POSES = [Pose([float(i), 0.0, 0.0], turned(10.0 * i)) for i in range(6)]
# Six offsets along x; offsets 2 and 3 see the same window (a duplicate view), and the
# centre offset is 3: its distinct window is the third.
SHARED_VIEWS = [[0, 0, 20], [4, 0, 20], [8, 0, 20], [8, 0, 20], [12, 0, 20], [16, 0, 20]]


def test_windows_round_trip_through_the_file_each_window_once(tmp_path):
    first = diagnosed("seq-01/frame-000", 0, SHARED_VIEWS, centre=3)
    # A portrait query: the window moves along y.
    second = diagnosed("seq-01/frame-007", 1, [[0, 0, 9], [0, 5, 9], [0, 10, 9]], centre=1)
    path = tmp_path / "diagnose_windows.npz"
    save_windows(path, [first, second], MAP_POSES)
    loaded = load_windows(path)
    assert [q.frame for q in loaded] == ["seq-01/frame-000", "seq-01/frame-007"]
    windows = loaded[0].windows
    assert windows.count == 5  # six offsets, five distinct windows
    keep = [0, 1, 2, 4, 5]
    assert windows.centre == 2
    assert np.array_equal(windows.positions[windows.centre], first.positions[first.centre])
    assert np.array_equal(windows.distances, first.distances[keep])
    assert np.array_equal(windows.positions, first.positions[keep])
    assert np.array_equal(windows.quaternions, first.quaternions[keep])
    assert np.allclose(windows.offsets, [0.0, 0.25, 0.5, 0.75, 1.0])
    assert windows.distance_scale == 0.75
    map_positions = np.array([p.position for p in MAP_POSES])
    map_quaternions = np.array([p.quaternion for p in MAP_POSES])
    assert np.array_equal(windows.neighbour_positions, map_positions[first.neighbours[keep]])
    assert np.array_equal(windows.neighbour_quaternions, map_quaternions[first.neighbours[keep]])
    assert np.array_equal(loaded[0].truth.position, first.truth.position)
    assert np.array_equal(loaded[0].truth.quaternion, first.truth.quaternion)
    portrait = loaded[1].windows
    assert portrait.count == 3 and portrait.centre == 1
    assert np.allclose(portrait.offsets, [0.0, 0.5, 1.0])
    assert np.array_equal(portrait.positions, second.positions)


def test_the_centre_offset_maps_to_the_window_it_shares(tmp_path):
    # The centre offset (2) repeats the window of offset 1: the first of them is kept.
    query = diagnosed("q", 2, [[0, 0, 8], [3, 0, 8], [3, 0, 8], [6, 0, 8]], centre=2)
    save_windows(tmp_path / "w.npz", [query], MAP_POSES)
    (loaded,) = load_windows(tmp_path / "w.npz")
    assert loaded.windows.count == 3 and loaded.windows.centre == 1
    assert np.array_equal(loaded.windows.positions[1], query.positions[2])


def test_queries_without_neighbours_load_without_them(tmp_path):
    query = diagnosed("q", 3, SHARED_VIEWS, centre=3, neighbours=False)
    save_windows(tmp_path / "w.npz", [query], MAP_POSES)
    (loaded,) = load_windows(tmp_path / "w.npz")
    assert loaded.windows.neighbour_positions is None
    assert loaded.windows.neighbour_quaternions is None


def test_saving_needs_queries_diagnosed_with_their_poses(tmp_path):
    query = diagnosed("q", 4, SHARED_VIEWS, centre=3)
    bare = QueryWindows(
        "q",
        query.crops,
        query.views,
        query.distances,
        query.position_errors,
        query.orientation_errors,
        query.centre,
        query.windows,
    )
    for queries in ([], [bare]):
        with pytest.raises(ValueError, match="poses"):
            save_windows(tmp_path / "w.npz", queries, MAP_POSES)
    assert not (tmp_path / "w.npz").exists()


def rewritten(source, target, **changes):
    with np.load(source) as data:
        arrays = {key: data[key] for key in data.files}
    for key, value in changes.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    np.savez(target, **arrays)
    return target


@pytest.mark.parametrize("kind", ["missing", "garbage", "truncated", "npy", "no keys", "format"])
def test_a_file_that_is_not_a_recording_is_a_data_error_naming_it(tmp_path, kind):
    good = tmp_path / "good.npz"
    save_windows(good, [diagnosed("q", 5, SHARED_VIEWS, centre=3)], MAP_POSES)
    path = tmp_path / f"{kind.replace(' ', '_')}.npz"
    if kind == "garbage":
        path.write_bytes(b"not numpy at all")
    elif kind == "truncated":
        path.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    elif kind == "npy":
        path = tmp_path / "array.npy"
        np.save(path, np.arange(4))
    elif kind == "no keys":
        rewritten(good, path, views=None, centres=None)
    elif kind == "format":
        rewritten(good, path, format=np.array(99))
    with pytest.raises(DataError) as raised:
        load_windows(path)
    assert str(path) in str(raised.value)
    if kind == "no keys":
        assert "views" in str(raised.value) and "centres" in str(raised.value)
    if kind == "format":
        assert "format 99" in str(raised.value)


def test_recorded_query_errors():
    windows = Windows(
        distances=np.array([1.0, 2.0]),
        positions=np.array([[1.0, -2.0, 1.5], [np.nan, 0.0, 0.0]]),
        quaternions=np.array([turned(30), IDENTITY]),
        offsets=np.array([0.0, 1.0]),
        centre=0,
    )
    query = RecordedQuery("q", windows, TRUTH)
    position, orientation = query.window_errors()
    assert position[0] == pytest.approx(1.0) and orientation[0] == pytest.approx(30.0)
    assert np.isinf(position[1]) and np.isinf(orientation[1])  # a failed window
    assert query.errors(TRUTH.position, -TRUTH.quaternion) == pytest.approx((0.0, 0.0))


# --- the study ------------------------------------------------------------------------


AROUND = np.array([[0.3, 0, 0], [-0.3, 0, 0], [0, 0.3, 0], [0, -0.3, 0]])  # about a map image


def study_query(frame, truth_seed, window_seed):
    """Five windows (the centre is entry 2); the window nearest the map is always the
    most accurate and never the centre, so the paper's rule is the oracle here. Every
    window's nearest map images sit around the truth, so retrieval consistency finds
    the best window too."""
    truth_rng = np.random.default_rng(truth_seed)
    truth = Pose(truth_rng.uniform(-5, 5, 3), turned(truth_rng.uniform(0, 180)))
    rng = np.random.default_rng(window_seed)
    errors = rng.uniform(0.5, 2.0, 5)
    best = rng.choice([0, 1, 3, 4])
    errors[best] = rng.uniform(0.02, 0.1)
    directions = rng.normal(size=(5, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    axes = rng.normal(size=(5, 3))
    quaternions = np.array(
        [multiply(turned(5 * e, a), truth.quaternion) for e, a in zip(errors, axes, strict=True)]
    )
    distances = rng.uniform(1.0, 1.5, 5)
    distances[best] = rng.uniform(0.6, 0.9)
    windows = Windows(
        distances=distances,
        positions=truth.position + directions * errors[:, None],
        quaternions=quaternions,
        offsets=np.linspace(0, 1, 5),
        centre=2,
        distance_scale=1.2,
        neighbour_positions=np.tile(truth.position + AROUND, (5, 1, 1)),
        neighbour_quaternions=np.tile(truth.quaternion, (5, 4, 1)),
    )
    return RecordedQuery(frame, windows, truth)


SEEDS = (0, 1)
TEST_FRAMES = [f"test/frame-{i:03d}" for i in range(10)]
VALIDATION_FRAMES = [f"train/frame-{i:03d}" for i in range(8)]


def recordings():
    """Per seed: validation queries (carved from training) and the test queries (the
    same frames and truths for every seed, each seed's own windows)."""
    validation = {
        s: [study_query(f, 100 + i, 1000 * s + i) for i, f in enumerate(VALIDATION_FRAMES)]
        for s in SEEDS
    }
    test = {
        s: [study_query(f, i, 1000 * s + 500 + i) for i, f in enumerate(TEST_FRAMES)] for s in SEEDS
    }
    return validation, test


@pytest.fixture(scope="module")
def studied():
    """The study of `recordings`, with every LearnedSelector.fit call's frames noted."""
    fitted_frames = []
    original = LearnedSelector.fit

    def spy(self, queries, position_errors, frames):
        fitted_frames.append(list(frames))
        return original(self, queries, position_errors, frames)

    validation, test = recordings()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(LearnedSelector, "fit", spy)
        report = study(validation, test)
    return report, fitted_frames


def test_study_answers_every_rule_paired_with_the_centre(studied):
    report, _ = studied
    settings = report["settings"]
    chosen = rule_study.ChosenSettings(settings["temperature"], settings["gate_threshold"], {}, {})
    expected = [*rules_of(chosen, LearnedSelector()), ORACLE]
    assert list(report["rules"]) == expected
    assert report["seeds"] == list(SEEDS)
    assert report["test_queries"] == len(TEST_FRAMES)
    assert report["validation_queries"] == {"0": 8, "1": 8}
    assert report["learned_selector_fitted_on"] == {"0": 8, "1": 8}
    for name, row in report["rules"].items():
        assert len(row["median_position_m"]["values"]) == len(SEEDS)
        assert np.isfinite(row["headroom_captured"])
        if name == REFERENCE:
            assert "vs_reference" not in row
        else:
            for kind in ("position_m", "orientation_deg"):
                assert {"median_difference", "bootstrap_95", "wilcoxon_p", "verdict"} <= set(
                    row["vs_reference"][kind]
                )
    rules = report["rules"]
    assert rules[REFERENCE]["headroom_captured"] == 0.0
    assert rules[ORACLE]["headroom_captured"] == pytest.approx(1.0)
    # The window nearest the map is the best window of every query here.
    paper = rules["min map distance (paper)"]
    assert paper["headroom_captured"] == pytest.approx(1.0)
    assert paper["vs_reference"]["position_m"]["verdict"] == "significantly lower"
    assert rules["retrieval consistency"]["headroom_captured"] == pytest.approx(1.0)
    assert rules["mean of all windows"]["headroom_captured"] < 1.0
    assert settings["temperature"] in TEMPERATURES
    assert set(settings["validation_median_position_m"]["temperature"]) == {
        f"{t:g}" for t in TEMPERATURES
    }


def test_the_learned_selector_is_fitted_on_validation_frames_only(studied):
    _, fitted_frames = studied
    assert len(fitted_frames) == len(SEEDS)
    for frames in fitted_frames:
        assert frames == VALIDATION_FRAMES
        assert not set(frames) & set(TEST_FRAMES)
    validation, _ = recordings()
    selector = fitted_selector(validation[1], seed=1)
    assert selector.fitted_on == tuple(VALIDATION_FRAMES)
    assert selector.seed == 1


def test_a_validation_frame_that_is_a_test_frame_is_refused():
    validation, test = recordings()
    validation[1] = [*validation[1], study_query(TEST_FRAMES[3], 3, 77)]
    with pytest.raises(ValueError, match="validation frames are test frames.*frame-003"):
        study(validation, test)


def test_the_seeds_must_agree():
    validation, test = recordings()
    with pytest.raises(ValueError, match="seeds"):
        study({0: validation[0]}, test)
    test[1] = test[1][:-1]
    with pytest.raises(ValueError, match="seed 1 answered other test queries"):
        study(validation, test)


def test_as_markdown_names_every_rule(studied):
    report, _ = studied
    markdown = as_markdown("GoogLeNet, stairs", report)
    assert markdown.startswith("## GoogLeNet, stairs: 10 test queries, seeds 0, 1")
    for name in report["rules"]:
        assert f"| {name} |" in markdown
    assert "| centre |" in markdown and "reference" in markdown
    assert "significantly lower" in markdown


def test_headroom_figure_writes_a_png(studied, tmp_path):
    report, _ = studied
    path = headroom_figure({"GoogLeNet": report, "ResNet": report}, tmp_path / "headroom.png")
    assert path == tmp_path / "headroom.png"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- settings from validation ---------------------------------------------------------


def three_windows(frame, nearest, centre_error, paper_error, spread=(0.5, 1.0)):
    """The centre (entry 1) and the window nearest the map (entry 0, relative distance
    `nearest`) off the truth by the given errors along x; entry 2 is 10 m off."""
    positions = TRUTH.position + np.array([[paper_error, 0, 0], [centre_error, 0, 0], [10, 0, 0]])
    windows = Windows(
        distances=nearest + np.array([0.0, *spread]),
        positions=positions,
        quaternions=np.tile(IDENTITY, (3, 1)),
        offsets=np.array([0.0, 0.5, 1.0]),
        centre=1,
    )
    return RecordedQuery(frame, windows, TRUTH)


def test_a_sharp_temperature_wins_where_the_nearest_window_is_right():
    # Off windows 0.05 map units further: only a small temperature ignores them.
    validation = [
        [three_windows(f"v{s}-{i}", 1.0, 5.0, 0.0, spread=(0.05, 0.1)) for i in range(5)]
        for s in SEEDS
    ]
    settings = choose_settings(validation)
    assert settings.temperature == min(TEMPERATURES)
    scores = [settings.temperature_scores[f"{t:g}"] for t in TEMPERATURES]
    assert scores == sorted(scores) and scores[0] < 1e-3


def test_a_flat_temperature_wins_where_the_windows_straddle_the_truth():
    # Two windows 1 m either side of the truth, 0.02 map units apart: their mean is exact.
    rng = np.random.default_rng(0)
    validation = [
        [
            three_windows(f"v{s}-{i}", 1.0, -1.0, 1.0, spread=(rng.uniform(0.01, 0.03), 9.0))
            for i in range(5)
        ]
        for s in SEEDS
    ]
    settings = choose_settings(validation)
    assert settings.temperature == max(TEMPERATURES)
    scores = [settings.temperature_scores[f"{t:g}"] for t in TEMPERATURES]
    assert scores == sorted(scores, reverse=True)


def gate_queries(paper_right):
    """Queries at a spread of nearest distances. Where `paper_right`, the nearest window
    is exact and the centre 1 m off; else the reverse. The right window's own error
    grows the further it is from the gate's best side, so one threshold wins."""
    rng = np.random.default_rng(1)
    validation = []
    for s in SEEDS:
        nearest = rng.uniform(0.2, 2.0, 20)
        if paper_right:
            rows = [three_windows(f"v{s}-{i}", r, 1.0, 0.1 * r) for i, r in enumerate(nearest)]
        else:
            rows = [
                three_windows(f"v{s}-{i}", r, 0.1 * (3 - r), 1.0) for i, r in enumerate(nearest)
            ]
        validation.append(rows)
    return validation


@pytest.mark.parametrize(
    "paper_right, quantile", [(True, min(GATE_QUANTILES)), (False, max(GATE_QUANTILES))]
)
def test_the_gate_threshold_of_smallest_validation_median_is_chosen(paper_right, quantile):
    validation = gate_queries(paper_right)
    settings = choose_settings(validation)
    nearest = [q.windows.relative_distances.min() for seed in validation for q in seed]
    thresholds = np.quantile(nearest, GATE_QUANTILES)
    assert list(settings.gate_scores) == [f"{t:.6g}" for t in thresholds]
    assert settings.gate_threshold == pytest.approx(np.quantile(nearest, quantile), rel=1e-5)
    best = min(settings.gate_scores.values())
    assert sum(score == best for score in settings.gate_scores.values()) == 1  # no tie
