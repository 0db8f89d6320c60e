"""refine=relative on a rendered room: the pose of queries between keyframes, the
flagged fallbacks of degenerate keyframe sets, its options, its state in a model file."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from relocfw import ConfigError, DataError, MapImage, Relocalizer
from relocfw.core.camera import SEVENSCENES_DEFAULT
from relocfw.core.geometry import orientation_error_deg
from relocfw.core.refinement import RefineQuery
from relocfw.core.values import Pose
from relocfw.model.model_file import load_model, save_model, stores_refiner
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.relative_refiner import RelativeRefiner
from tests.structure.textured_world import looking_at, make_world, render

pytest.importorskip("poselib")

CAMERA = SEVENSCENES_DEFAULT.scaled_to(320, 240)
MAP_POSITIONS = [[-0.45, 0.0, 0.0], [-0.15, 0.0, 0.0], [0.15, 0.0, 0.0], [0.45, 0.0, 0.0]]
MAP_POSITIONS += [[x, -0.2, -0.1] for x in (-0.3, 0.0, 0.3)]
QUERY_POSITIONS = [[-0.3, 0.05, 0.15], [0.0, 0.1, 0.2], [0.3, -0.05, 0.1]]
NETWORK_POSE = Pose(np.array([9.0, 9.0, 9.0]), np.array([1.0, 0.0, 0.0, 0.0]))


def map_pose(position: list[float]) -> Pose:
    return looking_at(position, [position[0] * 0.5, 0.0, 3.0])


def query_pose(position: list[float]) -> Pose:
    return looking_at(position, [-position[0] * 0.3, 0.0, 3.0])


@pytest.fixture(scope="module")
def room() -> dict:
    world = make_world(seed=0)
    poses = [map_pose(p) for p in MAP_POSITIONS]
    views = [
        MapImage(f"map-{n}", render(world, pose, CAMERA, supersample=1), pose, CAMERA)
        for n, pose in enumerate(poses)
    ]
    truths = [query_pose(p) for p in QUERY_POSITIONS]
    queries = [render(world, pose, CAMERA, supersample=1) for pose in truths]
    return {"views": views, "truths": truths, "queries": queries}


def descriptors_of(poses: list[Pose]) -> np.ndarray:
    """Descriptors that retrieve by position (what a trained network approximates)."""
    return np.stack([np.concatenate([p.position, p.quaternion]) for p in poses])


def asked(image: np.ndarray, truth: Pose) -> RefineQuery:
    return RefineQuery(image, NETWORK_POSE, descriptors_of([truth])[0])


@pytest.fixture(scope="module")
def fitted(room) -> RelativeRefiner:
    refiner = RelativeRefiner(count=4, max_features=512, quiet=True)
    refiner.fit(room["views"], descriptors_of([v.pose for v in room["views"]]))
    return refiner


def test_queries_between_keyframes_get_their_pose_without_depth(room, fitted):
    for image, truth in zip(room["queries"], room["truths"], strict=True):
        refined = fitted.refine(asked(image, truth))
        assert not refined.fell_back
        assert np.linalg.norm(refined.pose.position - truth.position) < 0.01  # 1-3 mm
        assert orientation_error_deg(refined.pose.quaternion, truth.quaternion) < 0.2
        assert refined.confidence >= 2 * fitted.min_inliers  # two keyframes or more
        assert set(refined.seconds) == {"retrieval", "features", "matching", "solve"}


def single_keyframe_refiner(room, views: list[MapImage]) -> RelativeRefiner:
    refiner = RelativeRefiner(count=4, max_features=512, quiet=True)
    refiner.fit(views, descriptors_of([v.pose for v in views]))
    return refiner


def test_degenerate_keyframe_sets_fall_back_flagged(room, fitted):
    image, truth = room["queries"][1], room["truths"][1]
    # One keyframe: one ray, a line and no point.
    alone = single_keyframe_refiner(room, room["views"][:1])
    # Keyframes that all stand in one place (turned copies of one view: no baseline
    # between them, so their rays start at one point).
    view = room["views"][1]
    same_place = [MapImage(f"copy-{n}", view.image, view.pose, CAMERA) for n in range(3)]
    stacked = single_keyframe_refiner(room, same_place)
    for refiner in (alone, stacked):
        refined = refiner.refine(asked(image, truth))
        assert refined.fell_back and refined.pose is NETWORK_POSE
        assert refined.confidence == 0.0
    # No matches: a query of no texture.
    blank = np.full_like(image, 128)
    refined = fitted.refine(asked(blank, truth))
    assert refined.fell_back and refined.pose is NETWORK_POSE


@pytest.mark.parametrize(
    "options, message",
    [
        ({"min_keyframes": 1}, "refine.min_keyframes must be at least 2, got 1"),
        ({"ratio": 1.5}, "refine.ratio must be above 0 and at most 1, got 1.5"),
        ({"max_error_px": 0}, "refine.max_error_px must be above 0, got 0"),
        ({"min_inliers": 4}, "refine.min_inliers must be at least 5, got 4"),
        ({"min_ray_angle_deg": 120}, "refine.min_ray_angle_deg must be above 0 and at most 90"),
    ],
)
def test_a_bad_option_is_refused_naming_its_key(options, message):
    with pytest.raises(ConfigError) as caught:
        RelativeRefiner(**options)
    assert str(caught.value).startswith(message)


@pytest.mark.parametrize(
    ("key", "value", "most"),
    [
        ("max_features", 2**40, 100000),
        ("count", 2**40, 1000),
        ("min_inliers", 2**40, 100000),
        ("min_keyframes", 2**40, 1000),
    ],
)
def test_a_size_beyond_any_use_is_refused_on_the_command_line_and_in_a_state(
    fitted, key, value, most
):
    # 2**40 features made every query raise in OpenCV's SIFT_create.
    message = rf"refine\.{key} must be at most {most}, got {value}"
    with pytest.raises(ConfigError, match=rf"^{message}"):
        RelativeRefiner(**{key: value})
    forged = dict(fitted.state(), **{key: torch.tensor(value)})
    with pytest.raises(DataError, match=rf"^refine=relative state: {message}"):
        RelativeRefiner().load_state(forged)


def test_a_map_without_cameras_is_refused_by_name(room):
    view = room["views"][0]
    frames = [MapImage("seq-01/frame-000007", view.image, view.pose, None)]
    with pytest.raises(ConfigError, match="refine=relative needs the camera intrinsics"):
        RelativeRefiner().check_map(frames)


def test_the_state_answers_the_same_and_a_damaged_one_is_named(room, fitted):
    state = fitted.state()
    assert "points" in state and state["points"].shape == (0, 3)  # no 3-D point stored
    loaded = RelativeRefiner(count=1, min_inliers=99)  # the state's options win
    loaded.load_state(state)
    assert (loaded.count, loaded.min_inliers) == (fitted.count, fitted.min_inliers)
    for image, truth in zip(room["queries"], room["truths"], strict=True):
        a, b = fitted.refine(asked(image, truth)), loaded.refine(asked(image, truth))
        assert np.array_equal(a.pose.position, b.pose.position)
        assert (a.confidence, a.fell_back) == (b.confidence, b.fell_back)
    broken = dict(state, keyframe_descriptors=state["keyframe_descriptors"][:2])
    with pytest.raises(DataError, match="refine=relative state: keyframe_descriptors"):
        RelativeRefiner().load_state(broken)
    with pytest.raises(DataError, match="refine=relative state: refine.min_keyframes"):
        RelativeRefiner().load_state(dict(state, min_keyframes=torch.tensor(1)))
    with pytest.raises(DataError, match="refine=relative state: offsets"):
        RelativeRefiner().load_state({k: v for k, v in state.items() if k != "offsets"})


@dataclass(frozen=True)
class Frame:
    """What Relocalizer.fit reads of a map image (as relocfw.data.frames.Frame)."""

    name: str
    camera: object
    depth_path: Path | None = None
    depth_units_per_metre: float = 1000.0


def test_a_model_file_keeps_the_refiner_and_answers_the_same(room, tmp_path):
    torch.manual_seed(0)
    network = {"input_size": 32, "width": 0.0625, "feature_dim": 16}
    refine = {"count": 4, "max_features": 512, "quiet": True}
    relocalizer = Relocalizer(
        PoseNet(**network), ExhaustiveIndex(), CentreCrop(), refiner=RelativeRefiner(**refine)
    )
    views = room["views"]
    frames = [Frame(v.name, CAMERA) for v in views]
    relocalizer.fit([v.image for v in views], [v.pose for v in views], frames=frames)
    assert stores_refiner(relocalizer)
    expected = [relocalizer.localize(q) for q in room["queries"]]
    assert sum(not a.fell_back for a in expected) >= 2  # real solves, not fallbacks
    options = {"backbone": network, "refine": refine}
    path = save_model(tmp_path / "m.relocfw", relocalizer, options, {"scene": "synthetic"})
    started = time.perf_counter()
    loaded = load_model(path)
    assert time.perf_counter() - started < 10
    assert isinstance(loaded.refiner, RelativeRefiner)
    for a, b in zip([loaded.localize(q) for q in room["queries"]], expected, strict=True):
        assert np.abs(a.pose.position - b.pose.position).max() <= 1e-6
        assert np.abs(a.pose.quaternion - b.pose.quaternion).max() <= 1e-6
        assert (a.fell_back, a.refine_confidence) == (b.fell_back, b.refine_confidence)
