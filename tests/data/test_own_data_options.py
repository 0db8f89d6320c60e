"""Own data, honestly: a default camera is noted, TUM's depth scale and the metric flag
are options, and a wrong option is one error naming its key.

A loader that falls back to a dataset's nominal intrinsics prints one note naming the
folder and the values. `dataset.depth_units_per_metre` reads a millimetre depth PNG (a
RealSense's) as metres. `dataset.metric=false` (TUM, plain folder) reaches the report
units and the refiner as COLMAP's does.
"""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from relocfw.core.camera import SEVENSCENES_COLOUR, PinholeCamera
from relocfw.core.errors import ConfigError
from relocfw.data.depth import read_frame_depth
from relocfw.data.folder import PoseFolder
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.data.tum import UNITS_NOTE, TumDataset
from relocfw.report.units import METRES, unit_of
from tests.cli_runs import relocfw_here
from tests.conftest import TINY_MODEL
from tests.data.formats import write_folder, write_tum


@pytest.fixture
def tum_root(tiny_scene, tmp_path):
    """lap1 and lap2 (train) and lap3 (test) with depth, from the tiny synthetic scene."""
    write_tum(tiny_scene, tmp_path, depth=True)
    return tmp_path


def with_scene_camera(root, lap: str) -> None:
    """The tiny scene's 48 x 36 camera for a lap, so its depth maps fit the camera."""
    (root / lap / "camera-intrinsics.txt").write_text("43.875 0 23.5\n0 43.875 17.5\n0 0 1\n")


def test_tum_without_intrinsics_notes_the_folder_and_the_values(tum_root, capsys):
    TumDataset(str(tum_root), ["lap1"], ["lap3"]).frames("test")
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1
    assert lines[0].startswith(f"note: {tum_root / 'lap3'}: no camera-intrinsics.txt")
    assert "fx=525 fy=525 cx=319.5 cy=239.5 for 640 x 480" in lines[0]


def test_a_sensor_named_folder_notes_its_sensor_values(tum_root, capsys):
    shutil.move(tum_root / "lap3", tum_root / "rgbd_dataset_freiburg1_xyz")
    TumDataset(str(tum_root), ["lap1"], ["rgbd_dataset_freiburg1_xyz"]).frames("test")
    err = capsys.readouterr().err
    assert f"note: {tum_root / 'rgbd_dataset_freiburg1_xyz'}:" in err
    assert "TUM's freiburg1 intrinsics" in err and "fx=517.3 fy=516.5" in err


def test_the_note_comes_once_per_folder_and_not_with_a_file(tum_root, capsys):
    with_scene_camera(tum_root, "lap1")
    dataset = TumDataset(str(tum_root), ["lap1"], ["lap3"])
    for _ in range(2):
        dataset.frames("train")
        dataset.frames("test")
    err = capsys.readouterr().err
    assert err.count("note:") == 1 and str(tum_root / "lap3") in err


def test_sevenscenes_without_intrinsics_notes_its_default(tiny_scene, tmp_path, capsys):
    scene = tmp_path / "room"
    shutil.copytree(tiny_scene, scene)
    (scene / "camera-intrinsics.txt").unlink()
    frames = load_sevenscenes(scene, None, "test")
    # 7-Scenes' nominal colour camera (the synthetic scene's depth is registered, so
    # no depth camera is named).
    assert {f.camera for f in frames} == {SEVENSCENES_COLOUR}
    err = capsys.readouterr().err
    assert err.startswith(f"note: {scene}: no camera-intrinsics.txt")
    assert "fx=525 fy=525 cx=320 cy=240" in err


def test_depth_units_per_metre_scales_the_same_png(tum_root):
    with_scene_camera(tum_root, "lap3")
    tum = TumDataset(str(tum_root), ["lap1"], ["lap3"]).frames("test")
    millimetres = TumDataset(str(tum_root), ["lap1"], ["lap3"], depth_units_per_metre=1000).frames(
        "test"
    )
    assert {f.depth_units_per_metre for f in millimetres} == {1000.0}
    for a, b in zip(tum, millimetres, strict=True):
        at_5000, at_1000 = read_frame_depth(a), read_frame_depth(b)
        valid = np.isfinite(at_5000)
        assert valid.any() and np.array_equal(valid, np.isfinite(at_1000))
        # The same stored value is 5x as many metres at 1000 units per metre.
        assert np.allclose(at_1000[valid], 5 * at_5000[valid], rtol=1e-6)


@pytest.mark.parametrize("value", [0, -1000, math.nan, math.inf, "mm", True, None])
def test_a_bad_depth_scale_is_one_config_error_naming_the_key(tum_root, value):
    with pytest.raises(ConfigError, match=r"^dataset\.depth_units_per_metre must be") as error:
        TumDataset(str(tum_root), ["lap1"], ["lap3"], depth_units_per_metre=value)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("loader", ["tum", "folder"])
def test_metric_false_is_model_units_as_for_colmap(tiny_scene, tmp_path, loader):
    if loader == "tum":
        write_tum(tiny_scene, tmp_path)

        def make(**options):
            return TumDataset(str(tmp_path), ["lap1"], ["lap3"], **options)
    else:
        write_folder(tiny_scene, tmp_path)

        def make(**options):
            return PoseFolder(str(tmp_path), **options)

    assert unit_of(make()) == METRES and make().units_note == ""
    plain = unit_of(make(metric=False))
    assert plain.name == "model units" and not plain.metric
    assert "dataset.metric=false" in plain.note and "not metres" in plain.note
    with pytest.raises(ConfigError, match="dataset.metric must be true or false, got 'yes'"):
        make(metric="yes")


def test_tum_units_note_names_the_option():
    assert UNITS_NOTE.endswith("not metres") and "dataset.metric=false" in UNITS_NOTE


@pytest.mark.parametrize("dataset", ["tum", "folder"])
def test_metric_false_reaches_the_refiner(dataset):
    overrides = [o for o in TINY_MODEL if not o.startswith("hydra.")]
    with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
        plain = compose(
            "config", overrides=[*overrides, f"dataset={dataset}", "refine=features_rgb"]
        )
        declared = compose(
            "config",
            overrides=[
                *overrides,
                f"dataset={dataset}",
                "dataset.metric=false",
                "refine=features_rgb",
            ],
        )
    assert plain.dataset.metric is True and plain.refine.metric is True
    assert declared.dataset.metric is False and declared.refine.metric is False


def test_the_folder_reads_its_intrinsics_file(tiny_scene, tmp_path):
    write_folder(tiny_scene, tmp_path)
    assert {f.camera for f in PoseFolder(str(tmp_path)).frames("test")} == {None}
    (tmp_path / "camera-intrinsics.txt").write_text("40 0 23.5\n0 41 17.5\n0 0 1\n")
    frames = PoseFolder(str(tmp_path)).frames("test")
    assert {f.camera for f in frames} == {PinholeCamera(40, 41, 23.5, 17.5, 48, 36)}


def test_the_command_line_composes_and_refuses_depth_when_not_metric(tiny_scene, tmp_path):
    write_tum(tiny_scene, tmp_path / "tum")
    tum = ["dataset=tum", f"dataset.root={tmp_path / 'tum'}", "dataset.metric=false"]
    refused = relocfw_here([*TINY_MODEL, *tum, "refine=features"], tmp_path)
    assert refused.returncode == 2
    assert refused.stderr.count("error:") == 1 and "Traceback" not in refused.stderr
    assert "(dataset.metric=false)" in refused.stderr


def test_the_command_line_names_a_bad_depth_scale(tiny_scene, tmp_path):
    write_tum(tiny_scene, tmp_path / "tum")
    args = ["dataset=tum", f"dataset.root={tmp_path / 'tum'}", "dataset.depth_units_per_metre=0"]
    result = relocfw_here([*TINY_MODEL, *args], tmp_path)
    assert result.returncode == 2
    assert result.stderr.count("error:") == 1 and "Traceback" not in result.stderr
    assert "dataset=tum: dataset.depth_units_per_metre must be a positive number" in result.stderr
