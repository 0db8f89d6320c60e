"""Test-time selection rules over a query's windows, on windows with a known answer."""

import numpy as np
import pytest

from relocfw.core.geometry import mean_quaternion, orientation_error_deg
from relocfw.core.values import Pose
from relocfw.core.window_rules import (
    FEATURE_NAMES,
    RULE_NAMES,
    LearnedSelector,
    Windows,
    centre,
    consensus,
    gated,
    geometric_median,
    min_distance,
    retrieval_consistency,
    robust_mean,
    rotation_median,
    rule_named,
    soft_min_distance,
    window_features,
)
from tests.rotations import axis_angle, multiply

TRUTH = Pose([1.0, 2.0, 3.0], [np.cos(np.radians(15)), 0.0, 0.0, np.sin(np.radians(15))])


def near(quaternion, degrees, rng):
    """`quaternion` turned by `degrees` about a random axis."""
    return multiply(axis_angle(rng.normal(size=3), degrees), quaternion)


def windows_of(positions, quaternions, distances=None, centre_entry=None, **options):
    n = len(positions)
    return Windows(
        distances=np.arange(n, dtype=float) + 1 if distances is None else np.asarray(distances),
        positions=np.asarray(positions, dtype=float),
        quaternions=np.asarray(quaternions, dtype=float),
        offsets=np.linspace(0.0, 1.0, n),
        centre=n // 2 if centre_entry is None else centre_entry,
        **options,
    )


def cluster_and_outliers(seed=0):
    """7 windows near TRUTH (5 cm, 2 deg), 3 far in position and orientation, shuffled.

    Returns the windows and the entries of the cluster's windows."""
    rng = np.random.default_rng(seed)
    positions = [TRUTH.position + rng.normal(0, 0.05, 3) for _ in range(7)]
    positions += [TRUTH.position + far for far in ([10, 0, 0], [0, -12, 0], [8, 8, 0])]
    quaternions = [near(TRUTH.quaternion, 2.0, rng) for _ in range(7)]
    quaternions += [
        axis_angle([1, 0, 0], 170),
        axis_angle([0, 1, 0], 120),
        axis_angle([1, 1, 0], 150),
    ]
    order = rng.permutation(10)
    windows = windows_of(
        np.array(positions)[order], np.array(quaternions)[order], rng.uniform(1, 2, 10)
    )
    return windows, set(np.flatnonzero(order < 7).tolist())


def position_gap(choice):
    return float(np.linalg.norm(choice.position - TRUTH.position))


def angle_gap(choice):
    return float(orientation_error_deg(choice.quaternion, TRUTH.quaternion))


# --- Windows --------------------------------------------------------------------------


def test_windows_measure_distances_in_map_image_units():
    windows = windows_of(
        np.zeros((3, 3)), np.tile([1.0, 0, 0, 0], (3, 1)), [2.0, 4.0, 6.0], distance_scale=2.0
    )
    assert windows.count == 3
    assert np.allclose(windows.relative_distances, [1.0, 2.0, 3.0])


@pytest.mark.parametrize(
    "change, message",
    [
        ({"positions": np.zeros((3, 2))}, "positions has shape"),
        ({"positions": np.zeros((2, 3))}, "positions has shape"),
        ({"quaternions": np.zeros((3, 3))}, "quaternions has shape"),
        ({"offsets": np.zeros((3, 1))}, "offsets has shape"),
        ({"centre": 3}, "centre 3 is not one of the 3 windows"),
        ({"centre": -1}, "centre -1"),
        ({"distance_scale": 0.0}, "distance_scale must be > 0"),
        ({"distance_scale": -1.0}, "distance_scale must be > 0"),
        ({"distance_scale": float("nan")}, "distance_scale must be > 0"),
    ],
)
def test_windows_refuse_inconsistent_arrays(change, message):
    fields = {
        "distances": np.ones(3),
        "positions": np.zeros((3, 3)),
        "quaternions": np.tile([1.0, 0, 0, 0], (3, 1)),
        "offsets": np.linspace(0, 1, 3),
        "centre": 1,
    }
    with pytest.raises(ValueError, match=message):
        Windows(**(fields | change))


def test_windows_need_at_least_one_window():
    with pytest.raises(ValueError, match="at least one window"):
        Windows(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), 0)


# --- the rules ------------------------------------------------------------------------


def test_centre_and_min_distance_answer_their_window():
    rng = np.random.default_rng(1)
    positions = rng.normal(size=(5, 3))
    quaternions = np.array([near(TRUTH.quaternion, 30, rng) for _ in range(5)])
    quaternions[3] *= -1  # the same rotation on the other hemisphere
    windows = windows_of(positions, quaternions, [0.5, 0.4, 0.9, 0.1, 0.1], centre_entry=2)
    middle = centre(windows)
    assert middle.window == 2 and np.array_equal(middle.position, positions[2])
    nearest = min_distance(windows)
    assert nearest.window == 3  # the first of the tied nearest windows
    assert np.array_equal(nearest.position, positions[3])
    assert np.allclose(nearest.quaternion, -quaternions[3]) and nearest.quaternion[0] > 0
    assert rule_named("centre") is centre and rule_named("min_distance") is min_distance


def test_soft_min_distance_spans_min_distance_to_the_plain_mean():
    rng = np.random.default_rng(2)
    positions = rng.normal(size=(6, 3))
    quaternions = np.array([near(TRUTH.quaternion, 20, rng) for _ in range(6)])
    windows = windows_of(positions, quaternions, [0.9, 0.7, 0.3, 0.8, 0.6, 1.0])
    sharp, paper = soft_min_distance(windows, 1e-6), min_distance(windows)
    assert np.allclose(sharp.position, paper.position)
    assert orientation_error_deg(sharp.quaternion, paper.quaternion) < 1e-4
    flat = soft_min_distance(windows, np.inf)
    assert flat.window is None  # a blend, no one window
    assert np.allclose(flat.position, positions.mean(axis=0))
    assert np.allclose(flat.quaternion, mean_quaternion(quaternions))
    # In between, the answer leans towards the nearer windows.
    middle = soft_min_distance(windows, 0.3)
    to_paper = np.linalg.norm(middle.position - paper.position)
    assert to_paper < np.linalg.norm(flat.position - paper.position)
    # Only distances relative to the map's own scale matter.
    scaled = windows_of(
        positions, quaternions, np.array(windows.distances) * 10, distance_scale=10.0
    )
    assert np.allclose(soft_min_distance(scaled, 0.3).position, middle.position)


def test_consensus_and_robust_mean_see_through_outlying_windows():
    windows, cluster = cluster_and_outliers()
    chosen = consensus(windows)
    assert chosen.window in cluster
    robust = robust_mean(windows)
    assert robust.window is None
    assert position_gap(robust) < 0.1 and angle_gap(robust) < 3.0
    plain = soft_min_distance(windows, np.inf)  # the plain mean of every window
    assert position_gap(plain) > 1.0 and angle_gap(plain) > 8.0


def test_consensus_is_indifferent_to_the_quaternions_sign():
    windows, cluster = cluster_and_outliers(seed=3)
    flipped = windows_of(windows.positions, -windows.quaternions, windows.distances)
    assert consensus(flipped).window == consensus(windows).window


def test_geometric_median_of_points_with_outliers():
    rng = np.random.default_rng(4)
    inliers = rng.normal(0, 0.1, size=(9, 3))
    outliers = rng.normal(0, 1, size=(4, 3)) + 100
    points = np.vstack([inliers, outliers])
    median = geometric_median(points)
    assert np.linalg.norm(median) < 0.3  # the mean is ~30 m away
    assert np.linalg.norm(points.mean(axis=0)) > 25
    # It minimises the sum of distances: no nudge does better.
    cost = np.linalg.norm(points - median, axis=1).sum()
    for step in np.vstack([np.eye(3), -np.eye(3)]) * 1e-3:
        assert cost <= np.linalg.norm(points - median - step, axis=1).sum()


def test_geometric_median_of_collinear_points_is_their_middle_one():
    points = np.zeros((5, 3))
    points[:, 0] = [0.0, 1.0, 2.0, 7.0, 50.0]
    assert np.allclose(geometric_median(points), [2.0, 0, 0], atol=1e-6)


def test_geometric_median_leaves_a_data_point_that_is_not_the_median():
    # The starting mean (0) falls on a data point held by 1 of 8 points, while the
    # median is where 6 of them sit.
    points = np.zeros((8, 3))
    points[0, 0] = -6.0
    points[2:, 0] = 1.0
    assert np.allclose(points.mean(axis=0), 0.0)
    assert np.allclose(geometric_median(points), [1.0, 0, 0], atol=1e-6)


def test_geometric_median_follows_the_weights():
    points = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]])
    assert np.allclose(geometric_median(points, np.array([5.0, 1.0, 1.0])), points[0])
    assert np.allclose(geometric_median(points, np.array([1.0, 5.0, 1.0])), points[1])


def test_rotation_median_is_robust_to_a_flipped_rotation():
    base = axis_angle([0, 0, 1], 40)
    cluster = np.array([multiply(axis_angle([0, 0, 1], d), base) for d in (-4, -2, 0, 2, 4)])
    flipped = multiply(axis_angle([0, 1, 1], 120), base)
    quaternions = np.vstack([cluster, flipped])
    assert orientation_error_deg(mean_quaternion(quaternions), base) > 8.0
    assert orientation_error_deg(rotation_median(quaternions), base) < 1.0
    # q and -q are one rotation: a window on the other hemisphere changes nothing.
    quaternions[[1, 5]] *= -1
    assert orientation_error_deg(rotation_median(quaternions), base) < 1.0


def test_retrieval_consistency_picks_the_window_its_map_images_agree_with():
    rng = np.random.default_rng(5)
    count, neighbours, agreeing = 6, 4, 4
    places = rng.uniform(-20, 20, size=(count, 3))  # where each window's map images are
    facings = np.array([near(TRUTH.quaternion, 60, rng) for _ in range(count)])
    neighbour_positions = places[:, None] + rng.normal(0, 0.1, size=(count, neighbours, 3))
    neighbour_quaternions = np.array(
        [[near(f, 1.0, rng) for _ in range(neighbours)] for f in facings]
    )
    # Every window's pose is metres and tens of degrees off its map images', but one.
    positions = places + rng.normal(0, 1, size=(count, 3)) * 3
    quaternions = np.array([near(f, 40, rng) for f in facings])
    positions[agreeing] = places[agreeing] + 0.02
    quaternions[agreeing] = near(facings[agreeing], 0.5, rng)
    windows = windows_of(
        positions,
        quaternions,
        neighbour_positions=neighbour_positions,
        neighbour_quaternions=neighbour_quaternions,
    )
    chosen = retrieval_consistency(windows)
    assert chosen.window == agreeing
    assert np.array_equal(chosen.position, positions[agreeing])
    assert rule_named("retrieval_consistency") is retrieval_consistency


def test_retrieval_consistency_without_neighbours_names_what_it_needs():
    windows, _ = cluster_and_outliers()
    with pytest.raises(ValueError, match="nearest map images"):
        retrieval_consistency(windows)


def test_gated_answers_the_nearest_window_only_above_its_threshold():
    rng = np.random.default_rng(6)
    positions = rng.normal(size=(5, 3))
    quaternions = np.array([near(TRUTH.quaternion, 10, rng) for _ in range(5)])
    # Nearest window: entry 4, relative distance 0.6 / 2 = 0.3; the centre is entry 2.
    windows = windows_of(positions, quaternions, [1.0, 0.8, 1.2, 0.9, 0.6], distance_scale=2.0)
    assert gated(windows, 0.1).window == min_distance(windows).window == 4
    assert gated(windows, 0.29).window == 4
    assert gated(windows, 0.3).window == 2  # not above: the centre crop
    assert gated(windows, 5.0).window == centre(windows).window == 2


# --- the learned selector ---------------------------------------------------------------


def test_window_features_are_scale_free_and_named():
    windows, _ = cluster_and_outliers()
    features = window_features(windows)
    assert features.shape == (10, len(FEATURE_NAMES) - 1)  # no neighbours recorded
    column = dict(zip(FEATURE_NAMES, features.T, strict=False))
    assert np.allclose(column["relative_distance"], windows.relative_distances)
    assert column["above_nearest"].min() == 0.0
    assert column["above_centre"][windows.centre] == 0.0
    assert sorted(column["distance_rank"]) == pytest.approx(np.linspace(0, 1, 10))
    assert column["off_centre"][windows.centre] == 0.0
    assert np.ptp(column["query_nearest"]) == 0.0
    # Scaled distances (with their map scale) and scaled positions read alike.
    scaled = windows_of(
        windows.positions * 10, windows.quaternions, windows.distances * 3, distance_scale=3.0
    )
    assert np.allclose(window_features(scaled), features)
    with_neighbours = windows_of(
        windows.positions,
        windows.quaternions,
        windows.distances,
        neighbour_positions=np.repeat(windows.positions[:, None], 3, axis=1),
        neighbour_quaternions=np.repeat(windows.quaternions[:, None], 3, axis=1),
    )
    assert window_features(with_neighbours).shape == (10, len(FEATURE_NAMES))


def consensus_queries(count, seed):
    """Queries whose best window is always the one at the others' robust centre: the
    others sit in pairs opposite each other about the truth (in position and angle);
    the best window's distance and place among the windows are random."""
    rng = np.random.default_rng(seed)
    queries, errors = [], []
    for _ in range(count):
        directions = rng.normal(size=(2, 3))
        steps = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        steps *= rng.uniform(0.5, 2.0, size=(2, 1))
        turns = [axis_angle(rng.normal(size=3), a) for a in rng.uniform(5, 20, 2)]
        offsets = [steps[0], -steps[0], steps[1], -steps[1], rng.normal(0, 0.01, 3)]
        quaternions = [multiply(t, TRUTH.quaternion) for t in turns]
        quaternions = [quaternions[0], multiply(turns[0] * [1, -1, -1, -1], TRUTH.quaternion),
                       quaternions[1], multiply(turns[1] * [1, -1, -1, -1], TRUTH.quaternion),
                       near(TRUTH.quaternion, 0.5, rng)]  # fmt: skip
        order = rng.permutation(5)
        positions = TRUTH.position + np.array(offsets)[order]
        windows = windows_of(positions, np.array(quaternions)[order], rng.uniform(0.5, 1.5, 5))
        queries.append(windows)
        errors.append(np.linalg.norm(positions - TRUTH.position, axis=1))
    return queries, errors


def test_learned_selector_learns_to_pick_the_consensus_window():
    queries, errors = consensus_queries(60, seed=7)
    frames = [f"val-{i}" for i in range(60)]
    selector = LearnedSelector(seed=0).fit(queries, errors, frames)
    assert selector.fitted_on == tuple(frames)
    fresh, fresh_errors = consensus_queries(20, seed=8)
    picked = [selector(w).window for w in fresh]
    best = [int(np.argmin(e)) for e in fresh_errors]
    assert np.mean(np.array(picked) == np.array(best)) >= 0.9
    assert [consensus(w).window for w in fresh] == best  # what it had to learn


def test_learned_selector_caps_failed_windows():
    queries, errors = consensus_queries(30, seed=9)
    errors[0] = errors[0].copy()
    errors[0][0] = np.inf  # a window whose pose was not finite
    selector = LearnedSelector(seed=1).fit(queries, errors, [f"v{i}" for i in range(30)])
    assert selector(queries[1]).window is not None


def test_learned_selector_must_be_fitted_first():
    windows, _ = cluster_and_outliers()
    with pytest.raises(ValueError, match="fit first"):
        LearnedSelector()(windows)
    assert LearnedSelector().fitted_on == ()


def test_rule_named_passes_its_setting_and_names_the_known_rules():
    windows, _ = cluster_and_outliers()
    for tau in (0.01, 1.0):
        expected = soft_min_distance(windows, tau)
        got = rule_named("soft_min_distance", tau=tau)(windows)
        assert np.array_equal(got.position, expected.position)
    plain_mean = soft_min_distance(windows, np.inf)
    assert np.array_equal(rule_named("mean")(windows).position, plain_mean.position)
    for threshold in (0.0, 1e9):
        expected = gated(windows, threshold)
        assert rule_named("gated", threshold=threshold)(windows).window == expected.window
    with pytest.raises(ValueError, match="unknown rule 'nearest'.*soft_min_distance"):
        rule_named("nearest")
    for name in RULE_NAMES:  # the names crop.rule accepts all resolve
        assert callable(rule_named(name))
