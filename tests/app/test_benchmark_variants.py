"""Benchmark helpers that decide what a benchmark row measures (no data needed)."""

import importlib
import types
from pathlib import Path

import numpy as np
import pytest

import relocfw.structure.tracks as tracks_module

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture
def oracle(monkeypatch):
    """benchmarks/rgb_settings_oracle.py, imported as its docstring runs it (-m)."""
    monkeypatch.syspath_prepend(str(BENCHMARKS.parent))
    return importlib.import_module("benchmarks.rgb_settings_oracle")


def test_partners_within_recording_filters_and_restores(oracle, monkeypatch):
    asked = []

    def library_choice(poses, cameras, depths, partners, low, high):
        asked.append(partners)
        # Best first, across two recordings.
        return [[1, 2, 3], [0, 2, 3], [3, 0, 1], [2, 1, 0]][: len(poses)]

    monkeypatch.setattr(tracks_module, "covisible_partners", library_choice)
    names = ["seq-01/frame-0", "seq-01/frame-1", "seq-02/frame-0", "seq-02/frame-1"]
    with oracle.partners_within_recording(names, enabled=True):
        chosen = tracks_module.covisible_partners([None] * 4, None, None, 1, 1.5, 20.0)
    # Every candidate asked for, then the best one of the image's own recording kept.
    assert asked == [4]
    assert chosen == [[1], [0], [3], [2]]
    assert tracks_module.covisible_partners is library_choice
    with oracle.partners_within_recording(names, enabled=False):
        assert tracks_module.covisible_partners is library_choice


def test_partners_within_recording_reaches_the_library_build(oracle, monkeypatch):
    # build_track_points looks the partner choice up in its module when it runs, so
    # the swap takes effect there: the build stops at the choice with what it chose.
    monkeypatch.setattr(
        tracks_module, "covisible_partners", lambda poses, *rest: [[1, 2], [0, 2], [0, 1]]
    )
    monkeypatch.setattr(tracks_module, "scene_depths", lambda poses: None)

    class ChosenError(Exception):
        pass

    def stop(features, poses, cameras, partners, settings, *progress):
        raise ChosenError(partners)

    monkeypatch.setattr(tracks_module, "pair_matches", stop)
    names = ["seq-01/frame-0", "seq-01/frame-1", "seq-02/frame-0"]
    within = oracle.partners_within_recording(names, enabled=True)
    with pytest.raises(ChosenError) as chosen, within:
        tracks_module.build_track_points([], [None] * 3, [], tracks_module.TrackSettings())
    assert chosen.value.args[0] == [[1], [0], []]
    within = oracle.partners_within_recording(names, enabled=True)
    with pytest.raises(ValueError, match="2 poses but 3 map image names"), within:
        tracks_module.covisible_partners([None] * 2, None, None, 1, 1.5, 20.0)


def test_partners_within_recording_restores_after_an_error(oracle):
    before = tracks_module.covisible_partners
    with pytest.raises(RuntimeError), oracle.partners_within_recording(["a/0"], enabled=True):
        raise RuntimeError("build failed")
    assert tracks_module.covisible_partners is before


@pytest.fixture
def colmap_points(monkeypatch):
    """benchmarks/colmap_points.py, imported as it runs (the script's own folder first)."""
    pytest.importorskip("poselib")
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    return importlib.import_module("colmap_points")


def built_rows(colmap_points, rows) -> dict:
    """Each row's refiner, as the benchmark composes it (no structure cache)."""
    return {label: colmap_points.composed_refiner(overrides, None) for label, overrides in rows}


def test_colmap_points_rows_are_the_shipped_configs(colmap_points):
    built = built_rows(colmap_points, colmap_points.ROWS)
    assert (built["features"].rematch, built["features"].rematch_answer) == (
        "near",
        "more_inliers",
    )
    assert built["features, one solve"].rematch == "none"
    assert built["features_colmap"].image_scale == 0.5
    assert built["features_colmap"].rematch == "near"
    rgb = built["features_rgb"]
    assert (rgb.count, rgb.max_error_px, rgb.rematch) == (20, 16.0, "near")
    assert rgb.triangulation["epipolar_px"] == 6.0
    assert rgb.triangulation["max_reprojection_px"] == 6.0
    assert all(refiner.metric is True for refiner in built.values())
    assert built["features_rgb, one solve"].rematch == "none"
    assert all(refiner.cache_dir is None for refiner in built.values())


def test_colmap_points_validation_rows_vary_one_setting_each(colmap_points):
    built = built_rows(colmap_points, colmap_points.VALIDATION_ROWS)
    settings = {
        label: (
            refiner.structure_source,
            refiner.image_scale,
            refiner.rematch,
            refiner.rematch_answer,
        )
        for label, refiner in built.items()
    }
    assert settings == {
        "features_colmap": ("colmap", 1.0, "none", "more_inliers"),
        "features_colmap, matching again": ("colmap", 1.0, "near", "more_inliers"),
        "features_colmap, SIFT at half size": ("colmap", 0.5, "none", "more_inliers"),
        "features_colmap, half size, matching again": ("colmap", 0.5, "near", "more_inliers"),
    }
    # Every row is paired against the defaults' row.
    assert {old for _, old in colmap_points.VALIDATION_PAIRS} == {"features_colmap"}


def test_poselib_loss_scale_passes_the_scale_and_restores(oracle, monkeypatch):
    poselib = pytest.importorskip("poselib")
    seen = []

    def library_solve(points_2d, points_3d, camera, ransac, bundle):
        seen.append(dict(bundle))
        return "pose", {}

    monkeypatch.setattr(poselib, "estimate_absolute_pose", library_solve)
    with oracle.poselib_loss_scale(2.0):
        assert (
            poselib.estimate_absolute_pose(None, None, None, {}, {"max_iterations": 5})[0] == "pose"
        )
    with oracle.poselib_loss_scale(0.0):
        poselib.estimate_absolute_pose(None, None, None, {}, {})
    assert seen == [{"max_iterations": 5, "loss_scale": 2.0}, {}]
    assert poselib.estimate_absolute_pose is library_solve


def test_poselib_loss_scale_reaches_relocfw_solver(oracle, monkeypatch):
    poselib = pytest.importorskip("poselib")
    from relocfw.core.camera import PinholeCamera
    from relocfw.structure.absolute_pose import solve_absolute_pose

    seen = []

    def library_solve(points_2d, points_3d, camera, ransac, bundle):
        seen.append((ransac["max_reproj_error"], dict(bundle)))
        return types.SimpleNamespace(q=[1.0, 0.0, 0.0, 0.0], t=[0.0, 0.0, 0.0]), {"num_inliers": 6}

    monkeypatch.setattr(poselib, "estimate_absolute_pose", library_solve)
    points_2d = np.random.default_rng(0).uniform(0, 100, (6, 2))
    points_3d = np.random.default_rng(1).uniform(1, 2, (6, 3))
    camera = PinholeCamera(100.0, 100.0, 50.0, 50.0, 100, 100)
    with oracle.poselib_loss_scale(3.0):
        answer = solve_absolute_pose(points_2d, points_3d, camera, 16.0, 4)
    assert answer.success
    assert seen == [(16.0, {"loss_scale": 3.0})]
