"""Model files (format 5) hold the refiner's map: a Relocalizer with refine=features or
features_rgb, saved and loaded with its map images and depth files gone, answers as
the one that wrote it; a damaged map is one DataError naming the refine part; a
format 4 file still loads as it did."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from relocfw import DataError, Relocalizer
from relocfw.core.camera import SEVENSCENES_DEFAULT
from relocfw.core.imaging import read_rgb
from relocfw.model.model_file import MODEL_FORMAT, load_model, save_model, stores_refiner
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.features_refiner import FeaturesRefiner
from relocfw.plugins.posenet import PoseNet
from tests.structure.textured_world import depth_map, looking_at, make_world, render

pytest.importorskip("poselib")

CAMERA = SEVENSCENES_DEFAULT.scaled_to(320, 240)
# Map cameras 0.3 m apart along x (two rows), looking at the back wall; queries between.
MAP_POSITIONS = [[-0.45, 0.0, 0.0], [-0.15, 0.0, 0.0], [0.15, 0.0, 0.0], [0.45, 0.0, 0.0]]
MAP_POSITIONS += [[x, -0.2, -0.1] for x in (-0.3, 0.0, 0.3)]
QUERY_POSITIONS = [[-0.3, 0.05, 0.15], [0.0, 0.1, 0.2], [0.3, -0.05, 0.1]]


@dataclass(frozen=True)
class Frame:
    """What Relocalizer.fit reads of a map image (as relocfw.data.frames.Frame)."""

    name: str
    camera: object
    depth_path: Path
    depth_units_per_metre: float = 1000.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Map images and depth PNGs written under one folder, and the query images."""
    import cv2

    root: Path = tmp_path_factory.mktemp("refiner_map") / "scene"
    root.mkdir()
    world = make_world(seed=0)
    poses, frames = [], []
    for number, position in enumerate(MAP_POSITIONS):
        pose = looking_at(position, [position[0] * 0.5, 0.0, 3.0])
        image = render(world, pose, CAMERA, supersample=1)
        cv2.imwrite(str(root / f"map-{number}.png"), image[:, :, ::-1])
        depth = np.nan_to_num(depth_map(world, pose, CAMERA), nan=0.0)
        cv2.imwrite(str(root / f"map-{number}.depth.png"), np.rint(depth * 1000).astype(np.uint16))
        poses.append(pose)
        frames.append(Frame(f"map-{number}", CAMERA, root / f"map-{number}.depth.png"))
    queries = [
        render(world, looking_at(p, [-p[0] * 0.3, 0.0, 3.0]), CAMERA, supersample=1)
        for p in QUERY_POSITIONS
    ]
    return {"root": root, "poses": poses, "frames": frames, "queries": queries}


def fitted(scene: dict, **options) -> tuple[Relocalizer, dict]:
    """A tiny network, an exhaustive index, the centre crop and refine=features with
    `options`, fitted on the scene's map images read from their files."""
    torch.manual_seed(0)
    network = {"input_size": 32, "width": 0.0625, "feature_dim": 16}
    refine = {"count": 3, "max_features": 512, "quiet": True, **options}
    relocalizer = Relocalizer(
        PoseNet(**network), ExhaustiveIndex(), CentreCrop(), refiner=FeaturesRefiner(**refine)
    )
    images = [read_rgb(scene["root"] / f"{f.name}.png") for f in scene["frames"]]
    relocalizer.fit(images, scene["poses"], frames=scene["frames"])
    return relocalizer, {"backbone": network, "refine": refine}


def saved(relocalizer: Relocalizer, options: dict, path: Path) -> Path:
    return save_model(path, relocalizer, options, {"scene": "synthetic"})


@pytest.fixture(scope="module")
def depth_model(scene, tmp_path_factory) -> tuple[Relocalizer, Path]:
    """refine=features fitted on the scene, and its model file."""
    relocalizer, options = fitted(scene)
    return relocalizer, saved(relocalizer, options, tmp_path_factory.mktemp("m") / "m.relocfw")


def assert_same_answers(got: list, expected: list) -> None:
    for a, b in zip(got, expected, strict=True):
        assert np.abs(a.pose.position - b.pose.position).max() <= 1e-6
        assert np.abs(a.pose.quaternion - b.pose.quaternion).max() <= 1e-6
        assert a.fell_back == b.fell_back
        assert a.refine_confidence == b.refine_confidence


@pytest.mark.parametrize("structure", ["depth", "triangulated"])
def test_a_loaded_structure_model_answers_as_the_run_without_its_map_images(
    scene, tmp_path, structure
):
    relocalizer, options = fitted(scene, structure=structure)
    assert stores_refiner(relocalizer)
    expected = [relocalizer.localize(q) for q in scene["queries"]]
    assert sum(not a.fell_back for a in expected) >= 2  # real solves, not fallbacks
    path = saved(relocalizer, options, tmp_path / "model.relocfw")
    moved = scene["root"].with_name(f"gone-{structure}")
    scene["root"].rename(moved)  # map images and depth files are gone
    try:
        started = time.perf_counter()
        loaded = load_model(path)
        seconds = time.perf_counter() - started
        assert isinstance(loaded.refiner, FeaturesRefiner)
        assert loaded.refiner is not relocalizer.refiner
        assert loaded.refiner.structure_source == structure
        assert_same_answers([loaded.localize(q) for q in scene["queries"]], expected)
    finally:
        moved.rename(scene["root"])
    count = len(scene["frames"])
    print(
        f"\n{structure}: {path.stat().st_size / count:.0f} bytes per map image "
        f"({count} images), load_model {seconds * 1000:.0f} ms"
    )


def test_the_stored_map_keeps_only_the_points_that_exist(scene, tmp_path):
    relocalizer, options = fitted(scene, structure="triangulated")
    structure = relocalizer.refiner.structure
    state = torch.load(saved(relocalizer, options, tmp_path / "m.relocfw"), weights_only=True)
    assert state["format"] == MODEL_FORMAT == 5
    stored = state["refine"]["state"]
    with_point = int(structure.point_counts().sum())
    keypoints = sum(len(f) for f in structure.features)
    assert 0 < with_point < keypoints
    assert stored["points"].shape == (with_point, 3)
    assert stored["descriptors"].shape == (keypoints, 128)
    assert stored["descriptors"].dtype == torch.uint8
    # The loaded map is the built one, up to the names a query never reads.
    loaded = FeaturesRefiner()
    loaded.load_state(stored)
    for a, b, pa, pb in zip(
        loaded.structure.features,
        structure.features,
        loaded.structure.points,
        structure.points,
        strict=True,
    ):
        assert np.array_equal(a.descriptors, b.descriptors)
        assert np.array_equal(a.keypoints, b.keypoints)
        assert np.array_equal(pa, pb, equal_nan=True)


def damage(state: dict, how: str) -> None:
    if how == "dtype":
        state["descriptors"] = state["descriptors"].float()
    elif how == "offsets":
        state["offsets"][2] = state["offsets"][-1] + 1
    elif how == "nan":
        state["points"][0, 1] = float("nan")
    elif how == "negative":
        state["point_keypoints"][0] = -1
    elif how == "missing":
        del state["keyframe_descriptors"]
    elif how == "not_a_tensor":
        state["cameras"] = [[585.0] * 6]


@pytest.mark.parametrize(
    ("how", "message"),
    [
        ("dtype", "descriptors must be torch.uint8"),
        ("offsets", "offsets must rise"),
        ("nan", "points hold NaN"),
        ("negative", "point_keypoints must be strictly increasing"),
        ("missing", "keyframe_descriptors must be a tensor"),
        ("not_a_tensor", "cameras must be a tensor, got list"),
    ],
)
def test_a_damaged_refiner_map_is_one_data_error_naming_the_refine_part(
    depth_model, tmp_path, how, message
):
    payload = torch.load(depth_model[1], weights_only=True)
    damage(payload["refine"]["state"], how)
    torch.save(payload, tmp_path / "damaged.relocfw")
    with pytest.raises(DataError, match=f"damaged model file \\(refine: .*{message}") as caught:
        load_model(tmp_path / "damaged.relocfw")
    assert "\n" not in str(caught.value)


def test_a_format_4_file_still_loads_and_answers_with_the_network(scene, depth_model, tmp_path):
    relocalizer, path = depth_model
    payload = torch.load(path, weights_only=True)
    # What format 4 wrote for this model: no refine part (refine=features was left out).
    payload["format"] = 4
    del payload["refine"]
    torch.save(payload, tmp_path / "format4.relocfw")
    loaded = load_model(tmp_path / "format4.relocfw")
    assert loaded.refiner is None
    plain = Relocalizer(relocalizer.backbone, relocalizer.index, CentreCrop())
    for query in scene["queries"]:
        a, b = loaded.localize(query), plain.localize(query)
        assert np.allclose(a.pose.position, b.pose.position, rtol=0, atol=1e-9)


def test_a_newer_format_is_refused_in_one_line(depth_model, tmp_path):
    payload = torch.load(depth_model[1], weights_only=True)
    payload["format"] = 6
    torch.save(payload, tmp_path / "format6.relocfw")
    with pytest.raises(DataError, match="model format 6"):
        load_model(tmp_path / "format6.relocfw")


def test_the_refiner_answers_with_its_stored_options(scene, tmp_path):
    # Saved without the refiner's options, the state still gives them back.
    relocalizer, options = fitted(scene, min_inliers=20, ratio=0.7)
    path = saved(relocalizer, {"backbone": options["backbone"]}, tmp_path / "m.relocfw")
    loaded = load_model(path).refiner
    assert (loaded.min_inliers, loaded.ratio, loaded.count, loaded.max_features) == (
        20,
        0.7,
        3,
        512,
    )


def test_a_compact_map_model_is_one_file_that_answers_as_the_run(scene, depth_model, tmp_path):
    # refine.map_store=compact: the run answers from a folder beside the structure
    # cache; the model file holds the compact arrays, so it answers with the map
    # images, depth files and that folder all gone.
    cache = tmp_path / "cache"
    relocalizer, options = fitted(scene, map_store="compact", cache_dir=str(cache))
    assert relocalizer.refiner.structure is None
    on_disk = relocalizer.refiner.compact.file_bytes()
    expected = [relocalizer.localize(q) for q in scene["queries"]]
    assert sum(not a.fell_back for a in expected) >= 2
    path = saved(relocalizer, options, tmp_path / "model.relocfw")
    stored = torch.load(path, weights_only=True)["refine"]["state"]
    assert stored["compact_points"].dtype == torch.float16 and "descriptors" not in stored
    moved = scene["root"].with_name("gone-compact")
    scene["root"].rename(moved)
    for folder in (cache / "structure").iterdir():
        folder.rename(tmp_path / f"gone-{folder.name}")
    try:
        loaded = load_model(path)
        assert loaded.refiner.map_store == "compact" and loaded.refiner.compact.folder is None
        assert_same_answers([loaded.localize(q) for q in scene["queries"]], expected)
    finally:
        moved.rename(scene["root"])
    # What the docs quote (docs/structure.md, "Large maps"): the refine part's bytes
    # per map image, and the map's bytes a fitted refiner holds in memory.
    count = len(scene["frames"])
    memory_refiner = depth_model[0].refiner
    memory_state = sum(t.nbytes for t in memory_refiner.state().values())
    compact_state = sum(t.nbytes for t in stored.values())
    in_memory = sum(
        f.keypoints.nbytes + f.descriptors.nbytes + p.nbytes
        for f, p in zip(
            memory_refiner.structure.features, memory_refiner.structure.points, strict=True
        )
    )
    print(
        f"\nrefine state bytes per map image: memory {memory_state / count:.0f}, compact "
        f"{compact_state / count:.0f}; map held in memory per image: StructureMap "
        f"{in_memory / count:.0f} (+ MatchIndex {memory_refiner.match_index.nbytes / count:.0f}), "
        f"compact {relocalizer.refiner.compact.resident_bytes() / count:.0f} (its folder "
        f"{on_disk / count:.0f} on disk)"
    )
