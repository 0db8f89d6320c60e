"""The map's structure: points against the truth, views without depth, the npz file,
the cache and the content key."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import orientation_error_deg
from relocfw.core.values import Pose
from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.features import LocalFeatures
from relocfw.structure.query_solver import localize_against
from relocfw.structure.structure_cache import cached_structure_map, structure_key
from relocfw.structure.structure_map import StructureMap
from relocfw.structure.triangulated_structure import build_by_triangulation
from relocfw.structure.two_view_structure import triangulation_partners
from tests.structure.textured_world import (
    depth_map,
    looking_at,
    surface_points,
    write_depth_png,
)


def point_errors(structure: StructureMap, scene, image: int) -> np.ndarray:
    """Distances in metres of image `image`'s 3-D points from the surface its
    keypoints' rays hit."""
    has_point = np.isfinite(structure.points[image]).all(axis=1)
    keypoints = structure.features[image].keypoints[has_point].astype(np.float64)
    truth = surface_points(scene.world, structure.poses[image], structure.cameras[image], keypoints)
    return np.linalg.norm(structure.points[image][has_point] - truth, axis=1)


def test_depth_points_lie_on_the_surface(synthetic_scene, depth_structure):
    assert depth_structure.source == "depth"
    assert depth_structure.names == ("view-0", "view-1")
    assert depth_structure.skipped_views == ()
    for image in range(2):
        assert depth_structure.points[image].dtype == np.float32
        assert depth_structure.point_counts()[image] > 900
        errors = point_errors(depth_structure, synthetic_scene, image)
        # The depth is read at the nearest pixel, the ray through the sub-pixel
        # keypoint: at most half a pixel of depth slope off.
        assert np.median(errors) < 0.002
        assert np.percentile(errors, 95) < 0.02


def test_triangulated_points_are_within_millimetres_of_the_truth(
    synthetic_scene, triangulated_structure
):
    assert triangulated_structure.source == "triangulated"
    assert triangulated_structure.skipped_views == ()
    for image in range(3):
        errors = point_errors(triangulated_structure, synthetic_scene, image)
        assert len(errors) > 500
        assert np.median(errors) < 0.005
        assert np.percentile(errors, 80) < 0.015


def test_the_triangulated_map_localizes_the_query(synthetic_scene, triangulated_structure):
    answer = localize_against(
        triangulated_structure, synthetic_scene.query_image, synthetic_scene.camera, [0, 1, 2]
    )
    assert answer.success
    truth = synthetic_scene.query_pose
    assert np.linalg.norm(answer.pose.position - truth.position) < 0.03
    assert orientation_error_deg(answer.pose.quaternion, truth.quaternion) < 1.0


def test_a_view_without_depth_is_kept_with_nan_points_and_listed(synthetic_scene, tmp_path):
    view = synthetic_scene.views[0]
    corrupt = tmp_path / "corrupt.depth.png"
    corrupt.write_bytes(b"not a png")
    views = [
        dataclasses.replace(view, depth_path=None, name="no-depth"),
        dataclasses.replace(view, depth_path=tmp_path / "missing.depth.png", name="missing"),
        dataclasses.replace(view, depth_path=corrupt, name="corrupt"),
        synthetic_scene.views[1],
    ]
    structure = build_from_depth(views, max_features=300, quiet=True)
    assert structure.names == ("no-depth", "missing", "corrupt", "view-1")
    for image in range(3):
        assert len(structure.features[image]) == 300  # features kept: queries may match
        assert np.isnan(structure.points[image]).all()
    assert structure.point_counts()[3] > 250
    reasons = {s.name: s.reason for s in structure.skipped_views}
    assert list(reasons) == ["no-depth", "missing", "corrupt"]
    assert "depth_path is None" in reasons["no-depth"]
    assert "missing.depth.png" in reasons["missing"]
    assert "corrupt.depth.png" in reasons["corrupt"]


def test_a_depth_map_without_any_reading_is_listed(synthetic_scene, tmp_path):
    empty = write_depth_png(np.full((480, 640), np.nan, np.float32), tmp_path / "empty.png")
    view = dataclasses.replace(synthetic_scene.views[0], depth_path=empty, name="empty")
    structure = build_from_depth([view], max_features=100, quiet=True)
    assert np.isnan(structure.points[0]).all()
    assert structure.skipped_views[0].name == "empty"
    assert "no keypoint has a depth reading" in structure.skipped_views[0].reason


def test_a_smaller_depth_map_of_the_same_aspect_is_scaled(synthetic_scene, tmp_path):
    view = synthetic_scene.views[0]
    half = depth_map(synthetic_scene.world, view.pose, view.camera.scaled_to(320, 240))
    path = write_depth_png(half, tmp_path / "half.depth.png")
    structure = build_from_depth([dataclasses.replace(view, depth_path=path)], 500, quiet=True)
    assert structure.skipped_views == ()
    errors = point_errors(structure, synthetic_scene, 0)
    assert len(errors) > 450
    assert np.median(errors) < 0.005  # a depth pixel covers two image pixels


def test_depth_in_other_units_is_read_in_its_units(synthetic_scene, tmp_path):
    view = synthetic_scene.views[0]
    path = write_depth_png(synthetic_scene.depths[0], tmp_path / "tum.png", 5000.0)
    tum_view = dataclasses.replace(view, depth_path=path, depth_units_per_metre=5000)
    structure = build_from_depth([tum_view], max_features=300, quiet=True)
    errors = point_errors(structure, synthetic_scene, 0)
    assert len(errors) == 300 and np.median(errors) < 0.002


def test_a_depth_map_of_another_aspect_is_one_error_naming_it(synthetic_scene, tmp_path):
    path = write_depth_png(np.ones((200, 320), np.float32), tmp_path / "squashed.depth.png")
    view = dataclasses.replace(synthetic_scene.views[0], depth_path=path)
    with pytest.raises(DataError, match="squashed.depth.png.*aspect ratio"):
        build_from_depth([view], 100, quiet=True)


def test_builders_refuse_what_is_not_a_list_of_views(synthetic_scene):
    with pytest.raises(DataError, match="empty"):
        build_from_depth([], quiet=True)
    with pytest.raises(DataError, match=r"views\[1\] must be a MapView"):
        build_from_depth([synthetic_scene.views[0], "view.png"], 10, quiet=True)
    with pytest.raises(DataError, match="sequence of MapView"):
        build_by_triangulation(synthetic_scene.views[0], quiet=True)
    with pytest.raises(ConfigError, match="max_features"):
        build_from_depth(synthetic_scene.views, max_features=0, quiet=True)
    with pytest.raises(ConfigError, match="min_angle_deg"):
        build_by_triangulation(synthetic_scene.views, min_angle_deg=-1, quiet=True)


def test_progress_is_shown_unless_quiet(synthetic_scene, capsys):
    build_from_depth(synthetic_scene.views[:1], max_features=50)
    assert "map structure from depth" in capsys.readouterr().err
    build_from_depth(synthetic_scene.views[:1], max_features=50, quiet=True)
    assert capsys.readouterr().err == ""


def test_partners_look_the_same_way_at_a_useful_baseline():
    forward = [0.0, 0.0, 10.0]
    poses = [
        looking_at([0.0, 0, 0], forward),
        looking_at([0.02, 0, 0], forward),  # too close to 0: no baseline
        looking_at([0.3, 0, 0], forward),
        looking_at([0.7, 0, 0], forward),
        looking_at([0.1, 0, 0], [10.0, 0, 0]),  # looks 90 degrees away
        looking_at([-2.0, 0, 0], forward),
    ]
    chosen = triangulation_partners(poses, partners=2, min_baseline_m=0.05)
    assert chosen[0] == [2, 3]
    assert chosen[2] == [1, 0]  # 0.28 m and 0.3 m
    assert chosen[4] == []  # nothing looks its way
    assert triangulation_partners(poses, 5, max_distance_m=1.0)[0] == [2, 3]
    assert triangulation_partners(poses, 5, max_axis_angle_deg=100)[0] == [4, 2, 3, 5]
    with pytest.raises(ConfigError, match="partners"):
        triangulation_partners(poses, partners=0)


def test_a_view_without_partners_is_listed(synthetic_scene):
    far = dataclasses.replace(
        synthetic_scene.views[2], pose=looking_at([0.0, -0.2, -0.1], [3.0, 0, 0.0]), name="away"
    )
    structure = build_by_triangulation(
        [*synthetic_scene.views[:2], far], max_features=200, partners=1, quiet=True
    )
    assert [s.name for s in structure.skipped_views] == ["away"]
    assert "no partner" in structure.skipped_views[0].reason
    assert np.isnan(structure.points[2]).all()


def test_save_and_load_give_the_same_map_and_answer(synthetic_scene, depth_structure, tmp_path):
    path = tmp_path / "map.npz"
    depth_structure.save(path)
    loaded = StructureMap.load(path)
    assert loaded.same_as(depth_structure)
    assert not loaded.same_as(dataclasses.replace(depth_structure, source="triangulated"))
    before = localize_against(
        depth_structure, synthetic_scene.query_image, synthetic_scene.camera, [0, 1]
    )
    after = localize_against(loaded, synthetic_scene.query_image, synthetic_scene.camera, [0, 1])
    assert (before.inliers, before.correspondences) == (after.inliers, after.correspondences)
    assert np.array_equal(before.pose.position, after.pose.position)
    assert np.array_equal(before.pose.quaternion, after.pose.quaternion)
    # uint8 descriptors: about a quarter of the float32 map's bytes.
    assert path.stat().st_size < 0.5 * sum(f.descriptors.nbytes for f in depth_structure.features)


def test_skipped_views_survive_a_round_trip(synthetic_scene, tmp_path):
    view = dataclasses.replace(synthetic_scene.views[0], depth_path=None, name="no-depth")
    structure = build_from_depth([view], max_features=50, quiet=True)
    structure.save(tmp_path / "map.npz")
    loaded = StructureMap.load(tmp_path / "map.npz")
    assert loaded.same_as(structure)
    assert loaded.skipped_views == structure.skipped_views


def test_a_damaged_or_foreign_file_is_one_error_naming_it(depth_structure, tmp_path):
    path = tmp_path / "map.npz"
    depth_structure.save(path)
    data = path.read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="truncated.npz"):
        StructureMap.load(truncated)
    foreign = tmp_path / "foreign.npz"
    np.savez_compressed(foreign, weights=np.zeros(3))
    with pytest.raises(DataError, match="foreign.npz.*not a usable relocfw structure map"):
        StructureMap.load(foreign)
    array = tmp_path / "array.npy"
    np.save(array, np.zeros(3))
    with pytest.raises(DataError, match="array.npy"):
        StructureMap.load(array)
    with pytest.raises(DataError, match="not found.*absent.npz"):
        StructureMap.load(tmp_path / "absent.npz")


def test_descriptors_that_are_not_rootsift_are_not_stored(depth_structure, tmp_path):
    features = LocalFeatures(np.zeros((1, 2)), np.full((1, 128), 2.0))
    odd = StructureMap(
        (features,), (np.zeros((1, 3)),), depth_structure.poses[:1], depth_structure.cameras[:1],
        ("odd",), "depth",
    )  # fmt: skip
    with pytest.raises(DataError, match=r"\[0, 1\]"):
        odd.save(tmp_path / "odd.npz")
    assert not (tmp_path / "odd.npz").exists()


def test_a_map_refuses_inconsistent_parts(depth_structure):
    with pytest.raises(DataError, match="points"):
        dataclasses.replace(depth_structure, points=(np.zeros((3, 3)), depth_structure.points[1]))
    with pytest.raises(DataError, match="names"):
        dataclasses.replace(depth_structure, names=("one",))
    with pytest.raises(DataError, match="source"):
        dataclasses.replace(depth_structure, source="lidar")


def test_the_cache_builds_once_then_loads(depth_structure, tmp_path):
    calls = []

    def build() -> StructureMap:
        calls.append(1)
        return depth_structure

    key = structure_key(
        depth_structure.names,
        depth_structure.poses,
        depth_structure.cameras,
        {"max_features": 1024},
    )
    first = cached_structure_map(tmp_path, key, build, quiet=True)
    second = cached_structure_map(tmp_path, key, build, quiet=True)
    assert len(calls) == 1
    assert first.same_as(depth_structure) and second.same_as(depth_structure)
    assert (tmp_path / "structure" / f"{key}.npz").is_file()
    (tmp_path / "structure" / f"{key}.npz").write_bytes(b"PK\x03\x04 broken")
    with pytest.raises(DataError, match=f"{key}.npz.*delete it"):
        cached_structure_map(tmp_path, key, build, quiet=True)
    with pytest.raises(ConfigError, match="hex"):
        cached_structure_map(tmp_path, "../escape", build, quiet=True)


def test_the_key_follows_names_poses_cameras_and_settings(depth_structure):
    names, poses, cameras = depth_structure.names, depth_structure.poses, depth_structure.cameras
    key = structure_key(names, poses, cameras, {"builder": "depth", "max_features": 1024})
    assert len(key) == 16 and int(key, 16) >= 0
    assert key == structure_key(names, poses, cameras, {"max_features": 1024, "builder": "depth"})
    moved = (Pose(poses[0].position + [0, 0, 1e-6], poses[0].quaternion), poses[1])
    others = [
        structure_key(("a", "b"), poses, cameras, {"builder": "depth", "max_features": 1024}),
        structure_key(names, moved, cameras, {"builder": "depth", "max_features": 1024}),
        structure_key(
            names,
            poses,
            (cameras[0].scaled_to(320, 240), cameras[1]),
            {"builder": "depth", "max_features": 1024},
        ),
        structure_key(names, poses, cameras, {"builder": "depth", "max_features": 2048}),
    ]
    assert len({key, *others}) == 5
    with pytest.raises(DataError, match="one of each"):
        structure_key(names[:1], poses, cameras, {})
