"""refine.keyframes=track: each query of a stream is matched against the keyframes near
its stream's last confident pose, retried by descriptor retrieval when that fails.

Most tests replace the solve (localize_against, as the plugin module names it) by a
script that records the keyframes of every call and answers a scripted outcome, so
each test pins which keyframes a query got and what was answered: tracking another
stream's pose, tracking after a fallback, keeping the failed attempt's answer instead
of the retry's, or remembering a pose across reset() would each fail one of them.
One test solves for real, so a solved pose is shown to work as the next prior.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from relocfw import ConfigError, DataError, MapImage, Pose
from relocfw.core.camera import SEVENSCENES_DEFAULT
from relocfw.core.refinement import RefineQuery
from relocfw.plugins import features_refiner
from relocfw.plugins.features_refiner import FeaturesRefiner
from relocfw.structure.query_solver import (
    MapViewpoints,
    StructureAnswer,
    keyframes_by_pose,
    localize_against,
)
from relocfw.structure.tracking_prior import stream_of
from tests.cli_runs import relocfw_here
from tests.conftest import TINY_OVERRIDES
from tests.structure.textured_world import looking_at, make_world, render, write_depth_png

SMALL_CAMERA = SEVENSCENES_DEFAULT.scaled_to(160, 120)
# Five map images at x = -1, -0.5, 0, 0.5, 1 m, all looking along +z.
MAP_X = [-1.0, -0.5, 0.0, 0.5, 1.0]
# Map descriptors along one dimension: a query at [0, 0] retrieves images 0 and 1.
DESCRIPTORS = [[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [6.0, 0.0], [10.0, 0.0]]
BY_DESCRIPTOR = [0, 1]
# A solved pose at x = 0.6 m: its two nearest map images are 3 and 4 (0.1, 0.4 m away),
# neither the descriptor's images nor those near the network's pose (x = 0: 2, 1).
SOLVED = looking_at([0.6, 0.0, 0.0], [0.6, 0.0, 3.0])
NEAR_SOLVED = [3, 4]
# Another solved pose at x = 0.1 m: nearest 2 and 3.
RETRIED = looking_at([0.1, 0.0, 0.0], [0.1, 0.0, 3.0])
NEAR_RETRIED = [2, 3]
FAILED_SECONDS = {"features": 0.25, "matching": 0.5, "solve": 1.0}
SOLVED_SECONDS = {"features": 0.125, "matching": 0.25, "solve": 2.0}


@pytest.fixture(scope="module")
def small_map(tmp_path_factory: pytest.TempPathFactory) -> list[MapImage]:
    """Five small textured map images with a flat depth map each (the images only give
    the map keypoints; the scripted solve never reads them)."""
    folder: Path = tmp_path_factory.mktemp("tracking_map")
    world = make_world(seed=1)
    depth = write_depth_png(np.full((120, 160), 2.5), folder / "flat.depth.png")
    views = []
    for number, x in enumerate(MAP_X):
        pose = looking_at([x, 0.0, 0.0], [x, 0.0, 3.0])
        image = render(world, pose, SMALL_CAMERA, supersample=1)
        views.append(MapImage(f"map/frame-{number}", image, pose, SMALL_CAMERA, depth))
    return views


class ScriptedSolve:
    """Stands in for localize_against: records each call's keyframes and answers the
    next scripted outcome (a Pose: solved there with 50 inliers; (Pose, n): with n
    inliers; None: failed)."""

    def __init__(self, outcomes: list[Pose | None]) -> None:
        self.outcomes = list(outcomes)
        self.keyframes: list[list[int]] = []
        self.given_features: list[object] = []  # each call's query_features
        self.known: list[object] = []  # each call's known_matches

    def __call__(self, structure, image, camera, keyframes, **options) -> StructureAnswer:
        self.keyframes.append([int(k) for k in keyframes])
        given = options.get("query_features")
        self.known.append(options.get("known_matches"))
        self.given_features.append(given)
        # The features "extracted" by this call: a fresh object unless given.
        features = given if given is not None else object()
        pose, inliers = self.outcomes.pop(0), 50
        if isinstance(pose, tuple):
            pose, inliers = pose
        if pose is None:
            return StructureAnswer(None, 3, 9, False, FAILED_SECONDS, query_features=features)
        return StructureAnswer(pose, inliers, 80, True, SOLVED_SECONDS, query_features=features)


def tracking(
    small_map, monkeypatch, outcomes, keyframes="track", rematch="none", **options
) -> tuple:
    refiner = FeaturesRefiner(
        keyframes=keyframes, count=2, max_features=256, quiet=True, rematch=rematch, **options
    )
    refiner.fit(small_map, np.asarray(DESCRIPTORS))
    solve = ScriptedSolve(outcomes)
    monkeypatch.setattr(features_refiner, "localize_against", solve)
    return refiner, solve


NETWORK_POSE = looking_at([0.0, 0.0, 0.0], [0.0, 0.0, 3.0])


def query(name: str | None) -> RefineQuery:
    blank = np.full((SMALL_CAMERA.height, SMALL_CAMERA.width, 3), 128, np.uint8)
    return RefineQuery(blank, NETWORK_POSE, np.zeros(2), name=name)


def test_the_scripted_poses_choose_other_keyframes_than_retrieval(small_map):
    # Guards the tests below: their three keyframe choices differ.
    poses = [view.pose for view in small_map]
    assert keyframes_by_pose(poses, SOLVED, 2) == NEAR_SOLVED
    assert keyframes_by_pose(poses, RETRIED, 2) == NEAR_RETRIED
    assert keyframes_by_pose(poses, NETWORK_POSE, 2) == [2, 1]


def test_the_next_frame_of_a_stream_is_matched_near_the_last_confident_pose(small_map, monkeypatch):
    refiner, solve = tracking(small_map, monkeypatch, [SOLVED, RETRIED])
    first = refiner.refine(query("seq-01/frame-000000"))
    assert not first.fell_back and first.pose is SOLVED
    second = refiner.refine(query("seq-01/frame-000001"))
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED]
    assert not second.fell_back and second.pose is RETRIED
    assert "tracking_retry" not in second.seconds  # one attempt, no retry


def test_another_stream_starts_from_retrieval(small_map, monkeypatch):
    refiner, solve = tracking(small_map, monkeypatch, [SOLVED, SOLVED, SOLVED])
    refiner.refine(query("seq-01/frame-000000"))
    refiner.refine(query("seq-02/frame-000000"))
    refiner.refine(query("seq-01/frame-000001"))  # seq-01's pose was kept meanwhile
    assert solve.keyframes == [BY_DESCRIPTOR, BY_DESCRIPTOR, NEAR_SOLVED]


def test_keyframes_by_descriptor_never_track(small_map, monkeypatch):
    refiner, solve = tracking(small_map, monkeypatch, [SOLVED, SOLVED], keyframes="descriptor")
    refiner.refine(query("seq-01/frame-000000"))
    refiner.refine(query("seq-01/frame-000001"))
    assert solve.keyframes == [BY_DESCRIPTOR, BY_DESCRIPTOR]


def test_queries_without_a_folder_or_name_are_one_stream(small_map, monkeypatch):
    refiner, solve = tracking(small_map, monkeypatch, [SOLVED, SOLVED, SOLVED])
    refiner.refine(query("frame-000000"))
    refiner.refine(query(None))
    refiner.refine(query("/frame-000002"))  # the recording "", not the unnamed stream
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED, BY_DESCRIPTOR]
    assert (stream_of("seq-03/frame-000042"), stream_of("a/b/frame")) == ("seq-03", "a/b")
    assert stream_of("frame") is None and stream_of(None) is None and stream_of("/f") == ""


def test_after_a_fallback_the_next_frame_starts_from_retrieval(small_map, monkeypatch):
    refiner, solve = tracking(small_map, monkeypatch, [SOLVED, None, None, RETRIED])
    refiner.refine(query("seq-01/frame-000000"))
    lost = refiner.refine(query("seq-01/frame-000001"))
    assert lost.fell_back and lost.pose is NETWORK_POSE
    refiner.refine(query("seq-01/frame-000002"))
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED, BY_DESCRIPTOR, BY_DESCRIPTOR]


def test_a_failed_tracking_attempt_is_retried_by_retrieval_and_its_pose_answered(
    small_map, monkeypatch
):
    refiner, solve = tracking(small_map, monkeypatch, [SOLVED, None, RETRIED, SOLVED])
    refiner.refine(query("seq-01/frame-000000"))
    retried = refiner.refine(query("seq-01/frame-000001"))
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED, BY_DESCRIPTOR]
    assert not retried.fell_back and retried.pose is RETRIED
    assert retried.confidence == 50.0  # the retry's inliers, not the failed attempt's 3
    # Both attempts' times, part by part, and the retry's own.
    for part in FAILED_SECONDS:
        assert retried.seconds[part] == FAILED_SECONDS[part] + SOLVED_SECONDS[part]
    assert 0.0 < retried.seconds["tracking_retry"] < 1.0 and "retrieval" in retried.seconds
    # The retry reuses the query's features from the failed attempt (not extracted twice).
    assert solve.given_features[1] is None and solve.given_features[2] is not None
    refiner.refine(query("seq-01/frame-000002"))  # the retry's pose is the next prior
    assert solve.keyframes[-1] == NEAR_RETRIED


def test_rematch_solves_again_near_the_first_answer_and_answers_the_second(small_map, monkeypatch):
    refiner, solve = tracking(
        small_map,
        monkeypatch,
        [SOLVED, RETRIED, SOLVED, RETRIED],
        keyframes="descriptor",
        rematch="near",
    )
    answer = refiner.refine(query("seq-01/frame-000000"))
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED]
    assert not answer.fell_back and answer.pose is RETRIED
    # The second solve reuses the first's features; both solves' times are counted.
    assert solve.given_features[0] is None and solve.given_features[1] is not None
    # ... and the first's matches per keyframe (one KnownMatches per query).
    assert solve.known[0] is not None and solve.known[1] is solve.known[0]
    refiner.refine(query("seq-01/frame-000001"))  # another query: its own
    assert solve.known[2] is not solve.known[0] and solve.known[3] is solve.known[2]
    for part in SOLVED_SECONDS:
        assert answer.seconds[part] == 2 * SOLVED_SECONDS[part]
    assert 0.0 < answer.seconds["rematch"] < 1.0


def test_rematch_keeps_the_first_answer_when_the_second_fails_and_skips_a_fallback(
    small_map, monkeypatch
):
    refiner, solve = tracking(
        small_map, monkeypatch, [SOLVED, None, None], keyframes="descriptor", rematch="near"
    )
    kept = refiner.refine(query("a"))
    assert not kept.fell_back and kept.pose is SOLVED and kept.confidence == 50.0
    # The failed second solve's time is counted, not lost into the network's part.
    for part in FAILED_SECONDS:
        assert kept.seconds[part] == SOLVED_SECONDS[part] + FAILED_SECONDS[part]
    assert 0.0 < kept.seconds["rematch"] < 1.0
    fallen = refiner.refine(query("b"))  # a first solve that fails is not matched again
    assert fallen.fell_back and fallen.pose is NETWORK_POSE
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED, BY_DESCRIPTOR]


def test_rematch_more_inliers_answers_the_solve_with_more_evidence(small_map, monkeypatch):
    # The second solve answers where it has at least the first's inliers, else the first.
    outcomes = [(SOLVED, 40), (RETRIED, 39), (SOLVED, 40), (RETRIED, 40), (SOLVED, 40), None]
    refiner, solve = tracking(
        small_map,
        monkeypatch,
        outcomes,
        keyframes="descriptor",
        rematch="near",
        rematch_answer="more_inliers",
    )
    fewer, tie, failed = (refiner.refine(query(name)) for name in "abc")
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED] * 3
    assert fewer.pose is SOLVED and fewer.confidence == 40.0
    assert tie.pose is RETRIED and tie.confidence == 40.0
    assert failed.pose is SOLVED and not failed.fell_back
    for part in SOLVED_SECONDS:  # both solves counted whichever answers
        assert fewer.seconds[part] == 2 * SOLVED_SECONDS[part]
    loaded = FeaturesRefiner()
    loaded.load_state(refiner.state())
    assert loaded.rematch_answer == "more_inliers"
    older = {k: v for k, v in refiner.state().items() if k != "rematch_answer"}
    loaded.load_state(older)  # a file from before the option answers second
    assert loaded.rematch_answer == "second"
    with pytest.raises(ConfigError, match="refine.rematch_answer must be one of second, more"):
        FeaturesRefiner(rematch_answer="best")


def test_rematch_more_inliers_is_what_the_track_follows(small_map, monkeypatch):
    # Frame 1's second solve has fewer inliers: the first answer (SOLVED) stands and is
    # the next frame's prior, so frame 2 is matched near SOLVED, not near RETRIED.
    outcomes = [(SOLVED, 40), (RETRIED, 39), (SOLVED, 40)]
    refiner, solve = tracking(
        small_map, monkeypatch, outcomes, rematch="near", rematch_answer="more_inliers"
    )
    first = refiner.refine(query("seq-01/frame-000000"))
    second = refiner.refine(query("seq-01/frame-000001"))
    assert first.pose is SOLVED and second.pose is SOLVED
    # Frame 2's own rematch would choose NEAR_SOLVED again: not solved twice.
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED, NEAR_SOLVED]


def test_rematch_does_not_solve_the_same_keyframes_again(small_map, monkeypatch):
    # keyframes=pose at x = 0 gives images 2, 1; a first answer there chooses them again.
    refiner, solve = tracking(
        small_map, monkeypatch, [NETWORK_POSE], keyframes="pose", rematch="near"
    )
    answer = refiner.refine(query("a"))
    assert solve.keyframes == [[2, 1]]
    assert answer.pose is NETWORK_POSE and not answer.fell_back
    assert answer.seconds["solve"] == SOLVED_SECONDS["solve"] and "rematch" in answer.seconds


def test_map_viewpoints_choose_as_the_poses_do(small_map):
    poses = [view.pose for view in small_map]
    viewpoints = MapViewpoints.of(poses)
    assert len(viewpoints) == 5 and viewpoints.positions.shape == (5, 3)
    for prior in (SOLVED, RETRIED, NETWORK_POSE):
        assert keyframes_by_pose(viewpoints, prior, 3) == keyframes_by_pose(poses, prior, 3)
    with pytest.raises(DataError, match="a StructureMap or a sequence of Poses"):
        MapViewpoints.of([poses[0], "not a pose"])


def test_rematch_union_adds_the_first_solves_keyframes(small_map, monkeypatch):
    refiner, solve = tracking(
        small_map, monkeypatch, [SOLVED, RETRIED], keyframes="descriptor", rematch="union"
    )
    answer = refiner.refine(query("a"))
    assert solve.keyframes == [BY_DESCRIPTOR, BY_DESCRIPTOR + NEAR_SOLVED]
    assert answer.pose is RETRIED
    # A keyframe in both sets is matched once.
    refiner, solve = tracking(
        small_map, monkeypatch, [RETRIED, SOLVED], keyframes="pose", rematch="union"
    )
    refiner.refine(query("a"))  # the network's pose at x = 0: images 2, 1
    assert solve.keyframes == [[2, 1], [2, 1, 3]]  # near RETRIED (x = 0.1): 2, 3


def test_rematch_union_after_a_lost_track_adds_the_retrys_keyframes(small_map, monkeypatch):
    # Frame 1: by descriptor, then union near SOLVED. Frame 2: the track near frame 1's
    # answer fails, the retry by descriptor solves RETRIED, and the union adds the
    # retry's keyframes (not the failed track's) to those near RETRIED.
    outcomes = [SOLVED, SOLVED, None, RETRIED, RETRIED]
    refiner, solve = tracking(small_map, monkeypatch, outcomes, rematch="union")
    refiner.refine(query("seq-01/frame-000000"))
    answer = refiner.refine(query("seq-01/frame-000001"))
    assert solve.keyframes == [
        BY_DESCRIPTOR,
        BY_DESCRIPTOR + NEAR_SOLVED,
        NEAR_SOLVED,
        BY_DESCRIPTOR,
        BY_DESCRIPTOR + NEAR_RETRIED,
    ]
    assert answer.pose is RETRIED and not answer.fell_back
    assert "tracking_retry" in answer.seconds and "rematch" in answer.seconds


def test_rematch_answers_the_track_and_is_kept_in_the_state(small_map, monkeypatch):
    outcomes = [SOLVED, RETRIED, SOLVED, SOLVED]
    refiner, solve = tracking(small_map, monkeypatch, outcomes, rematch="near")
    refiner.refine(query("seq-01/frame-000000"))
    refiner.refine(query("seq-01/frame-000001"))
    # The second frame tracks the first frame's rematched answer, RETRIED, then is
    # matched again near its own.
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED, NEAR_RETRIED, NEAR_SOLVED]
    loaded = FeaturesRefiner(rematch="union")
    loaded.load_state(refiner.state())
    assert loaded.rematch == "near"
    older = {k: v for k, v in refiner.state().items() if k != "rematch"}
    loaded.load_state(older)  # a file from before the option answers without it
    assert loaded.rematch == "none"
    with pytest.raises(DataError, match="rematch must be in 0..2"):
        loaded.load_state({**refiner.state(), "rematch": torch.tensor(3)})
    with pytest.raises(ConfigError, match="refine.rematch must be one of none, near, union"):
        FeaturesRefiner(rematch=True)


def test_reset_forgets_every_stream(small_map, monkeypatch):
    refiner, solve = tracking(small_map, monkeypatch, [SOLVED, SOLVED, SOLVED, SOLVED])
    refiner.refine(query("seq-01/frame-000000"))
    refiner.refine(query("seq-02/frame-000000"))
    refiner.reset()
    refiner.refine(query("seq-01/frame-000001"))
    refiner.refine(query("seq-02/frame-000001"))
    assert solve.keyframes == [BY_DESCRIPTOR] * 4


def test_a_non_finite_network_pose_does_not_stop_tracking(small_map, monkeypatch):
    # keyframes=pose must fall back on a NaN network pose; tracking does not need it.
    refiner, solve = tracking(small_map, monkeypatch, [SOLVED, SOLVED])
    nan_pose = Pose(np.full(3, np.nan), np.array([1.0, 0.0, 0.0, 0.0]))
    blank = query(None).image
    for number in range(2):
        name = f"seq-01/frame-{number:06d}"
        refined = refiner.refine(RefineQuery(blank, nan_pose, np.zeros(2), name=name))
        assert not refined.fell_back and refined.pose is SOLVED
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED]


def test_a_solved_pose_is_the_next_frames_prior_for_real(synthetic_scene, monkeypatch):
    pytest.importorskip("poselib")
    scene = synthetic_scene
    views = [MapImage(v.name, v.image, v.pose, v.camera, v.depth_path) for v in scene.views[:2]]
    refiner = FeaturesRefiner(keyframes="track", count=1, quiet=True)
    refiner.fit(views, np.eye(2))
    chosen: list[list[int]] = []

    def recording(structure, image, camera, keyframes, **options):
        chosen.append(list(keyframes))
        return localize_against(structure, image, camera, keyframes, **options)

    monkeypatch.setattr(features_refiner, "localize_against", recording)
    # Retrieval picks view 1 (descriptor [0, 1]); the solved pose is nearer view 0.
    answers = [
        refiner.refine(RefineQuery(scene.query_image, NETWORK_POSE, np.array([0.0, 1.0]), name=n))
        for n in ("seq-01/frame-000000", "seq-01/frame-000001")
    ]
    near = keyframes_by_pose(refiner.poses, answers[0].pose, 1)
    assert chosen == [[1], near]
    for answer in answers:
        assert not answer.fell_back
        assert np.linalg.norm(answer.pose.position - scene.query_pose.position) < 0.01


def fitted_state(small_map) -> dict[str, torch.Tensor]:
    refiner = FeaturesRefiner(keyframes="track", count=2, max_features=256, quiet=True)
    refiner.fit(small_map, np.asarray(DESCRIPTORS))
    return refiner.state()


def test_a_saved_tracking_refiner_loads_tracking(small_map, monkeypatch):
    state = fitted_state(small_map)
    loaded = FeaturesRefiner(keyframes="descriptor")
    loaded.load_state(state)
    assert loaded.keyframes == "track"
    solve = ScriptedSolve([SOLVED, SOLVED])
    monkeypatch.setattr(features_refiner, "localize_against", solve)
    loaded.refine(query("seq-01/frame-000000"))
    loaded.refine(query("seq-01/frame-000001"))
    assert solve.keyframes == [BY_DESCRIPTOR, NEAR_SOLVED]


@pytest.mark.parametrize(("code", "keyframes"), [(0, "descriptor"), (1, "pose")])
def test_older_keyframe_codes_load_as_before(small_map, code, keyframes):
    state = fitted_state(small_map)
    state["keyframes"] = torch.tensor(code)
    loaded = FeaturesRefiner(keyframes="track")
    loaded.load_state(state)
    assert loaded.keyframes == keyframes


@pytest.mark.parametrize("code", [7, 3, -1])
def test_a_forged_keyframes_code_is_one_data_error_naming_it(small_map, code):
    state = fitted_state(small_map)
    state["keyframes"] = torch.tensor(code)
    with pytest.raises(DataError) as caught:
        FeaturesRefiner().load_state(state)
    message = str(caught.value)
    assert message.startswith("refine=features state: keyframes must be in 0..2")
    assert f"got {code}" in message and "2 track" in message and "\n" not in message


def test_a_bogus_keyframes_choice_lists_track(tmp_path):
    args = [*TINY_OVERRIDES, "refine=features", "refine.keyframes=bogus"]
    result = relocfw_here(args, tmp_path)
    assert result.returncode == 2, result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert line == (
        "error: refine=features: refine.keyframes must be one of descriptor, pose, track, "
        "got 'bogus'"
    )
    assert not (tmp_path / "cache" / "checkpoints").exists()  # refused before training


def test_image_scale_and_match_points_only_are_kept_in_the_state(small_map):
    refiner = FeaturesRefiner(
        count=2,
        max_features=256,
        image_scale=0.5,
        match_points_only=False,
        ransac_min_iterations=64,
        quiet=True,
    )
    refiner.fit(small_map, np.asarray(DESCRIPTORS))
    loaded = FeaturesRefiner(image_scale=1.0, match_points_only=True)
    loaded.load_state(refiner.state())
    assert (loaded.image_scale, loaded.match_points_only) == (0.5, False)
    assert loaded.ransac_min_iterations == 64
    assert len(loaded.match_index.codes) == sum(len(f) for f in loaded.structure.features)


def test_a_state_from_before_the_options_answers_as_it_did(small_map):
    # Files written before image_scale and match_points_only: SIFT at full size and
    # matching against every keypoint, whatever the loading refiner's defaults.
    state = FeaturesRefiner(count=2, max_features=256, quiet=True)
    state.fit(small_map, np.asarray(DESCRIPTORS))
    older = {
        k: v for k, v in state.state().items() if k not in ("image_scale", "match_points_only")
    }
    loaded = FeaturesRefiner(image_scale=0.5, match_points_only=True)
    loaded.load_state(older)
    assert (loaded.image_scale, loaded.match_points_only) == (1.0, False)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("image_scale", torch.tensor(1.5, dtype=torch.float64), "image_scale"),
        ("match_points_only", torch.tensor(2), "match_points_only must be 0 or 1"),
        ("ransac_min_iterations", torch.tensor(2**40), "at most 100000"),
        ("ransac_min_iterations", torch.tensor(0), "ransac_min_iterations"),
    ],
)
def test_a_forged_scale_or_flag_is_one_data_error(small_map, key, value, message):
    state = fitted_state(small_map)
    state[key] = value
    with pytest.raises(DataError, match=message):
        FeaturesRefiner().load_state(state)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"image_scale": 2.0}, "refine.image_scale must be in"),
        ({"match_points_only": "yes"}, "refine.match_points_only must be true or false"),
        ({"ransac_min_iterations": 0}, "refine.ransac_min_iterations"),
    ],
)
def test_impossible_speed_options_are_named(options, message):
    with pytest.raises(ConfigError, match=message):
        FeaturesRefiner(**options)
