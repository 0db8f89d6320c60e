"""What makes a structure map trustworthy: a cache key that sees everything the map
depends on and a file that records it, depth maps read at a plausible scale, a clear
refusal of refine=features without depth, a flagged fallback for a non-finite
network pose, and the metric bound scaled on a map that is not metric."""

from __future__ import annotations

import dataclasses
import os

import cv2
import numpy as np
import pytest

from relocfw import ConfigError, DataError, MapImage, Pose, RefineQuery
from relocfw.plugins.features_refiner import FeaturesRefiner
from relocfw.structure import structure_cache
from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.query_solver import keyframes_by_pose
from relocfw.structure.structure_cache import cached_structure_map, structure_key
from relocfw.structure.structure_map import StructureMap

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def map_images(scene, scale: float = 1.0, depth: bool = True) -> list[MapImage]:
    """The synthetic scene's map views as a refiner takes them; positions times
    `scale` (a map in other units than metres)."""
    return [
        MapImage(
            view.name,
            view.image,
            Pose(view.pose.position * scale, view.pose.quaternion),
            view.camera,
            view.depth_path if depth else None,
        )
        for view in scene.views
    ]


def fitted(scene, **options) -> FeaturesRefiner:
    images = map_images(scene)
    refiner = FeaturesRefiner(quiet=True, **options)
    refiner.fit(images, np.eye(len(images)), quiet=True)
    return refiner


# --- the cache key and the key a file records ------------------------------------


def key_of(structure: StructureMap, settings: dict) -> str:
    return structure_key(structure.names, structure.poses, structure.cameras, settings)


def test_a_cache_file_recording_another_key_is_rebuilt_with_a_note(
    depth_structure, tmp_path, capsys
):
    key = key_of(depth_structure, {"max_features": 1024})
    path = tmp_path / "structure" / f"{key}.npz"
    # A file of other settings copied under this key's name (or one without a key).
    stale = dataclasses.replace(depth_structure, skipped_views=())
    stale.save(path, key="0123456789abcdef")
    built = []

    def build() -> StructureMap:
        built.append(1)
        return depth_structure

    answer = cached_structure_map(tmp_path, key, build, quiet=True)
    assert built == [1], "a file recording another key was used"
    assert answer.same_as(depth_structure)
    assert "records key 0123456789abcdef, not" in capsys.readouterr().err
    # Rebuilt over it, now recording its key: the next call reuses it.
    assert cached_structure_map(tmp_path, key, build, quiet=True).same_as(depth_structure)
    assert built == [1]


def test_the_key_sees_the_opencv_and_relocfw_versions(depth_structure, monkeypatch):
    before = key_of(depth_structure, {})
    monkeypatch.setattr(cv2, "__version__", "0.0.1")
    with_other_opencv = key_of(depth_structure, {})
    monkeypatch.setattr(structure_cache, "VERSION", "0.0.1")
    with_other_relocfw = key_of(depth_structure, {})
    assert len({before, with_other_opencv, with_other_relocfw}) == 3


def test_the_cache_key_sees_depth_contents_of_the_same_size_and_time(tmp_path):
    depth = tmp_path / "frame.depth.png"
    depth.write_bytes(b"first")
    os.utime(depth, ns=(1, 1))
    pose = Pose(np.zeros(3), IDENTITY)
    view = MapImage("frame", np.zeros((4, 6, 3), np.uint8), pose, None, depth)
    refiner = FeaturesRefiner()
    before = refiner.settings([view])
    depth.write_bytes(b"other")  # re-made, same size, its times kept (cp -p)
    os.utime(depth, ns=(1, 1))
    assert refiner.settings([view]) != before


def test_the_cache_key_holds_every_triangulation_parameter():
    pose = Pose(np.zeros(3), IDENTITY)
    view = MapImage("frame", np.zeros((4, 6, 3), np.uint8), pose)
    settings = FeaturesRefiner(structure="triangulated").settings([view])
    assert settings["build"] == {
        "method": "tracks",
        "partners": 6,
        "min_partner_angle_deg": 1.5,
        "max_partner_angle_deg": 20.0,
        "epipolar_px": 4.0,
        "max_reprojection_px": 4.0,
        "min_views": 2,
        "min_angle_deg": 1.5,
        "ratio": 0.8,
    }
    changed = FeaturesRefiner(structure="triangulated", triangulation={"epipolar_px": 3.0})
    assert changed.settings([view])["build"]["epipolar_px"] == 3.0
    # The earlier two-view builder stays selectable, with its own parameters.
    two_view = FeaturesRefiner(structure="triangulated", triangulation={"method": "two_view"})
    assert two_view.settings([view])["build"] == {
        "method": "two_view",
        "partners": 3,
        "max_partner_distance_m": None,
        "min_baseline_m": 0.05,
        "max_axis_angle_deg": 30.0,
        "min_angle_deg": 2.0,
        "max_reprojection_px": 4.0,
        "ratio": 0.8,
    }


def test_the_cache_key_holds_the_image_scale_but_not_at_full_size():
    pose = Pose(np.zeros(3), IDENTITY)
    view = MapImage("frame", np.zeros((4, 6, 3), np.uint8), pose)
    full = FeaturesRefiner(image_scale=1.0).settings([view])
    half = FeaturesRefiner(image_scale=0.5).settings([view])
    # Full size keeps the key maps had before the option (their caches still found).
    assert "image_scale" not in full and half["image_scale"] == 0.5
    assert {k: v for k, v in half.items() if k != "image_scale"} == full


# --- refine=features without depth -----------------------------------------------


def test_a_map_without_depth_files_is_refused_before_training(synthetic_scene):
    with pytest.raises(ConfigError, match="none of the 3 map images has one.*features_rgb"):
        FeaturesRefiner().check_map(map_images(synthetic_scene, depth=False))


def test_a_map_whose_depth_files_are_all_missing_is_refused_when_fitted(synthetic_scene, tmp_path):
    images = [
        dataclasses.replace(image, depth_path=tmp_path / f"{image.name}.depth.png")
        for image in map_images(synthetic_scene)
    ]
    with pytest.raises(ConfigError, match="no usable depth in any of the 3.*features_rgb"):
        FeaturesRefiner(quiet=True).fit(images, np.eye(3), quiet=True)


# --- a non-finite network pose ----------------------------------------------------


@pytest.mark.parametrize(
    "pose",
    [
        Pose(np.full(3, np.nan), IDENTITY),
        Pose(np.zeros(3), np.full(4, np.nan)),
    ],
    ids=["nan_position", "nan_quaternion"],
)
def test_a_non_finite_network_pose_falls_back_flagged(synthetic_scene, pose):
    refiner = fitted(synthetic_scene, keyframes="pose", count=2)
    # The query is map image 0: keyframes 0..1 picked blindly would solve it.
    query = RefineQuery(synthetic_scene.views[0].image, pose, np.zeros(3))
    answer = refiner.refine(query)
    assert answer.fell_back is True
    assert answer.pose is pose


def test_keyframes_near_a_non_finite_pose_are_refused(depth_structure):
    with pytest.raises(DataError, match="NaN or infinity"):
        keyframes_by_pose(depth_structure, Pose(np.full(3, np.nan), IDENTITY), 1)


# --- the depth scale --------------------------------------------------------------


@pytest.mark.parametrize(
    "units, message",
    [
        (1.0, r"median depth 3\.\d+e\+03 m .*millimetres read as metres"),
        (1e6, r"median depth 0\.003\d* m .*depth_units_per_metre too large"),
    ],
)
def test_depth_of_an_implausible_scale_is_refused_naming_the_file(synthetic_scene, units, message):
    view = dataclasses.replace(synthetic_scene.views[0], depth_units_per_metre=units)
    with pytest.raises(DataError, match=message) as caught:
        build_from_depth([view], quiet=True)
    assert str(caught.value).startswith(str(view.depth_path))


# --- a map that is not metric -----------------------------------------------------


def test_a_map_in_other_units_scales_the_smallest_baseline(synthetic_scene):
    # Centimetre-sized units of 100 m: the views stand 0.004-0.006 units apart, under
    # the 0.05 m bound taken as 0.05 units, so no view would have a partner.
    scale = 0.01
    images = map_images(synthetic_scene, scale)
    refiner = FeaturesRefiner(
        structure="triangulated", metric=False, quiet=True, triangulation={"method": "two_view"}
    )
    assert refiner.build_parameters(images)["min_baseline_m"] == pytest.approx(
        0.5 * 0.3742 * scale, rel=1e-3
    )
    refiner.fit(images, np.eye(3), quiet=True)
    metric = fitted(synthetic_scene, structure="triangulated", triangulation={"method": "two_view"})
    assert refiner.skipped_views == ()
    scaled_points = np.concatenate(refiner.structure.points)
    metric_points = np.concatenate(metric.structure.points)
    both = np.isfinite(scaled_points).all(axis=1) & np.isfinite(metric_points).all(axis=1)
    assert both.sum() >= 0.95 * np.isfinite(metric_points).all(axis=1).sum() > 100
    # The same map in other units; a point whose partners' checks fell the other way
    # at the bounds (a median of one triangulation, not two) moves by under 1%.
    same = np.isclose(scaled_points[both], metric_points[both] * scale, rtol=1e-4, atol=0)
    assert same.all(axis=1).mean() > 0.9
    np.testing.assert_allclose(scaled_points[both], metric_points[both] * scale, rtol=0.02)


def test_depth_is_refused_on_a_map_that_is_not_metric(synthetic_scene):
    # Refused once the map images are known (a COLMAP model's points would serve at
    # any scale), and before any network is trained: check_map runs first.
    refiner = FeaturesRefiner(structure="depth", metric=False)
    with pytest.raises(ConfigError, match="not metric.*features_rgb"):
        refiner.check_map(map_images(synthetic_scene))
    with pytest.raises(ConfigError, match="not metric.*features_rgb"):
        refiner.fit(map_images(synthetic_scene), np.eye(len(synthetic_scene.views)))
