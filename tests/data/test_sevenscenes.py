import re
import shutil

import cv2
import numpy as np
import pytest

from relocfw.core.camera import SEVENSCENES_COLOUR, SEVENSCENES_DEPTH, PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import pose_to_matrix
from relocfw.core.imaging import read_rgb
from relocfw.data.depth import read_frame_depth
from relocfw.data.intrinsics import read_intrinsics_matrix
from relocfw.data.sevenscenes import (
    REGISTERED_MARKER,
    SEVENSCENES_DEPTH_TO_COLOUR,
    SevenScenes,
    load_sevenscenes,
    read_pose_file,
    read_split,
)


def test_real_stairs_frames_load(stairs_sample):
    train = SevenScenes(stairs_sample, "stairs").frames("train")
    test = load_sevenscenes(stairs_sample, "stairs", "test")
    assert [f.name for f in train][:3] == [f"seq-02/frame-00000{i}" for i in range(3)]
    assert {f.name.split("/")[0] for f in train} == {"seq-02", "seq-03"}
    assert {f.name.split("/")[0] for f in test} == {"seq-01", "seq-04"}
    assert len(train) == len(test) == 6
    image = read_rgb(train[0].image_path)
    assert image.shape == (480, 640, 3) and image.dtype == np.uint8


def test_real_pose_text_parses_to_the_same_matrix(stairs_sample):
    # Microsoft's own format: leading spaces, tabs, CRLF, exponents like e-001.
    path = stairs_sample / "stairs" / "seq-01" / "frame-000000.pose.txt"
    raw = path.read_bytes()
    assert b"\t" in raw and b"e-001" in raw
    matrix = read_pose_file(path)
    assert matrix[0, 0] == pytest.approx(0.93817085)
    assert matrix[0, 3] == pytest.approx(-1.4903377)
    frame = next(f for f in load_sevenscenes(stairs_sample, "stairs", "test"))
    assert np.allclose(pose_to_matrix(frame.pose), matrix, atol=1e-4)


def test_split_files_with_crlf(stairs_sample):
    assert read_split(stairs_sample / "stairs" / "TrainSplit.txt") == [2, 3]


@pytest.fixture
def scene_copy(tiny_scene, tmp_path):
    copy = tmp_path / "room"
    shutil.copytree(tiny_scene, copy)
    return copy


def test_corrupt_image_is_named(scene_copy):
    bad = scene_copy / "seq-01" / "frame-000002.color.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(DataError, match="cannot decode") as error:
        read_rgb(bad)
    assert str(bad) in str(error.value)


def test_missing_pose_is_named(scene_copy):
    missing = scene_copy / "seq-01" / "frame-000001.pose.txt"
    missing.unlink()
    with pytest.raises(DataError, match="pose file not found") as error:
        load_sevenscenes(scene_copy, None, "train")
    assert str(missing) in str(error.value)


@pytest.mark.parametrize(
    "text, message",
    [
        ("1 0 0 0\n0 2 0 0\n0 0 1 0\n0 0 0 1\n", "not a rigid transform"),
        ("1 0 0\n0 1 0\n0 0 1\n", "expected 16 numbers"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 x\n", "not a pose file"),
        ("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "NaN"),
    ],
)
def test_bad_pose_files_are_named(scene_copy, text, message):
    path = scene_copy / "seq-02" / "frame-000003.pose.txt"
    path.write_text(text)
    with pytest.raises(DataError, match=message) as error:
        load_sevenscenes(scene_copy, None, "train")
    assert str(path) in str(error.value)


def test_bad_split_line_names_file_and_line(scene_copy):
    (scene_copy / "TestSplit.txt").write_text("sequence3\nseq four\n")
    with pytest.raises(DataError, match=r"TestSplit.txt:2"):
        load_sevenscenes(scene_copy, None, "test")


def test_missing_root_and_scene(tmp_path):
    with pytest.raises(DataError, match="dataset.root"):
        SevenScenes(tmp_path / "nope", "chess")
    with pytest.raises(DataError, match="dataset.scene"):
        SevenScenes(tmp_path, "chess")


def test_sequence_lists_replace_the_split_files(stairs_sample):
    dataset = SevenScenes(stairs_sample, "stairs", train_sequences=[1, 2], test_sequences=[3])
    assert {f.name.split("/")[0] for f in dataset.frames("train")} == {"seq-01", "seq-02"}
    assert {f.name.split("/")[0] for f in dataset.frames("test")} == {"seq-03"}
    # Only the list given is replaced; the other split still reads its file.
    only_test = SevenScenes(stairs_sample, "stairs", test_sequences=[4])
    assert {f.name.split("/")[0] for f in only_test.frames("train")} == {"seq-02", "seq-03"}
    assert {f.name.split("/")[0] for f in only_test.frames("test")} == {"seq-04"}


@pytest.mark.parametrize(
    "options, message",
    [
        ({"train_sequences": [1, 2], "test_sequences": [2]}, "share [2]"),
        # TrainSplit.txt lists 2 and 3: a test list of [3] alone would leak.
        ({"test_sequences": [3]}, "train [2, 3] and test [3] share [3]"),
        ({"train_sequences": [1, 4]}, "train [1, 4] and test [1, 4] share [1, 4]"),
        ({"train_sequences": []}, "dataset.train_sequences must be a non-empty list"),
        ({"test_sequences": [0]}, "dataset.test_sequences: sequence numbers are integers >= 1"),
        ({"test_sequences": 3}, "dataset.test_sequences must be a non-empty list"),
    ],
)
def test_bad_sequence_lists_name_the_key(stairs_sample, options, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        SevenScenes(stairs_sample, "stairs", **options)


def test_a_listed_sequence_that_is_missing_names_the_key(stairs_sample):
    with pytest.raises(DataError, match=r"dataset.train_sequences: sequence folder not found"):
        SevenScenes(stairs_sample, "stairs", train_sequences=[9]).frames("train")


# ------------------------------------------------------------ camera and depth


def write_intrinsics(path, fx, fy, cx, cy):
    path.write_text(f"{fx} 0 {cx}\n0 {fy} {cy}\n0 0 1\n")
    return path


def test_the_scene_folders_intrinsics_win_over_the_roots(scene_copy):
    # scene_copy is tmp_path/room: tmp_path plays the dataset root.
    write_intrinsics(scene_copy.parent / "camera-intrinsics.txt", 500, 501, 20, 15)
    frames = SevenScenes(scene_copy.parent, "room").frames("train")
    own = read_intrinsics_matrix(scene_copy / "camera-intrinsics.txt", 48, 36)
    assert own.fx == pytest.approx(43.875) and all(f.camera == own for f in frames)


def test_the_roots_intrinsics_sized_like_the_images(scene_copy):
    (scene_copy / "camera-intrinsics.txt").unlink()
    write_intrinsics(scene_copy.parent / "camera-intrinsics.txt", 500, 501, 20.5, 15)
    for frames in (
        SevenScenes(scene_copy.parent, "room").frames("test"),
        load_sevenscenes(scene_copy, None, "test"),  # the scene folder as root
    ):
        assert {f.camera for f in frames} == {PinholeCamera(500, 501, 20.5, 15, 48, 36)}


def test_without_an_intrinsics_file_the_7scenes_default(scene_copy):
    (scene_copy / "camera-intrinsics.txt").unlink()
    frames = load_sevenscenes(scene_copy, None, "train")
    # The synthetic scene says its depth is registered: no depth camera.
    assert {f.camera for f in frames} == {SEVENSCENES_COLOUR}
    assert {f.depth_camera for f in frames} == {None}
    (scene_copy / REGISTERED_MARKER).unlink()
    frames = load_sevenscenes(scene_copy, None, "train")
    assert {(f.camera, f.depth_camera) for f in frames} == {(SEVENSCENES_COLOUR, SEVENSCENES_DEPTH)}
    assert all(f.depth_to_colour is SEVENSCENES_DEPTH_TO_COLOUR for f in frames)


def test_colour_focal_sets_the_nominal_colour_camera(scene_copy):
    (scene_copy / "camera-intrinsics.txt").unlink()
    (scene_copy / REGISTERED_MARKER).unlink()
    frames = SevenScenes(scene_copy, None, colour_focal=529.5).frames("train")
    assert {f.camera for f in frames} == {PinholeCamera(529.5, 529.5, 320, 240, 640, 480)}
    assert {f.depth_camera for f in frames} == {SEVENSCENES_DEPTH}
    # With a depth file, the colour camera is scaled to the images' size like the default.
    write_intrinsics(scene_copy / "camera-intrinsics.txt", 43.875, 43.875, 23.5, 17.5)
    frames = load_sevenscenes(scene_copy, None, "test", colour_focal=529.5)
    expected = PinholeCamera(529.5, 529.5, 320, 240, 640, 480).scaled_to(48, 36)
    assert {f.camera for f in frames} == {expected}
    assert expected.fx == pytest.approx(529.5 * 48 / 640)


@pytest.mark.parametrize("value", [0, -525.0, float("nan"), float("inf"), "wide", True])
def test_a_colour_focal_that_is_not_a_focal_length_names_the_key(scene_copy, value):
    with pytest.raises(ConfigError, match=r"dataset\.colour_focal"):
        SevenScenes(scene_copy, None, colour_focal=value)


@pytest.mark.parametrize("registered", [True, False])
def test_colour_focal_beside_a_colour_file_is_refused(scene_copy, registered):
    # The file describes the colour camera (registered depth, or intrinsics_for=colour):
    # a user's calibration wins, so a second focal length is a contradiction.
    if not registered:
        (scene_copy / REGISTERED_MARKER).unlink()
    dataset = SevenScenes(scene_copy, None, intrinsics_for="colour", colour_focal=532)
    with pytest.raises(ConfigError, match=r"dataset\.colour_focal=532.*camera-intrinsics\.txt"):
        dataset.frames("train")


def test_colour_focal_leaves_the_trained_models_key_alone():
    # The network never sees a camera: the same images and poses train the same model.
    from omegaconf import OmegaConf

    from relocfw.app.methods import dataset_settings

    def settings(focal: float | None) -> dict:
        dataset = {"_target_": "relocfw.data.sevenscenes.SevenScenes", "root": "r"}
        return dataset_settings(OmegaConf.create({"dataset": {**dataset, "colour_focal": focal}}))

    assert settings(525.0) == settings(532.0) == settings(None)


@pytest.mark.parametrize("fx, noted", [(525 * 48 / 640, True), (585 * 48 / 640, False)])
def test_a_colour_looking_depth_file_is_noted(scene_copy, capsys, fx, noted):
    (scene_copy / REGISTERED_MARKER).unlink()
    write_intrinsics(scene_copy / "camera-intrinsics.txt", fx, fx, 24, 18)
    frames = load_sevenscenes(scene_copy, None, "train")  # intrinsics_for="depth"
    assert all(f.depth_camera.fx == pytest.approx(fx) for f in frames)
    notes = [line for line in capsys.readouterr().err.splitlines() if "intrinsics_for" in line]
    assert len(notes) == int(noted)
    if noted:
        assert "dataset.intrinsics_for=colour" in notes[0] and "camera-intrinsics.txt" in notes[0]
    load_sevenscenes(scene_copy, None, "train", intrinsics_for="colour")
    assert "intrinsics_for" not in capsys.readouterr().err


def test_real_stairs_frames_have_the_default_cameras_and_no_depth(stairs_sample):
    frames = SevenScenes(stairs_sample, "stairs").frames("test")
    assert all(f.camera == SEVENSCENES_COLOUR and f.depth_path is None for f in frames)
    assert all(f.depth_camera == SEVENSCENES_DEPTH for f in frames)


def test_depth_paths_where_the_depth_maps_are(scene_copy):
    missing = scene_copy / "seq-01" / "frame-000002.depth.png"
    missing.unlink()
    frames = load_sevenscenes(scene_copy, None, "train")
    without = [f.name for f in frames if f.depth_path is None]
    assert without == ["seq-01/frame-000002"]
    for frame in frames:
        if frame.depth_path is not None:
            assert frame.depth_path.is_file() and frame.depth_path.parent == frame.image_path.parent
            assert frame.depth_path.name == frame.name.split("/")[1] + ".depth.png"
            assert frame.depth_units_per_metre == 1000


@pytest.mark.parametrize("where", ["scene", "root"])
def test_a_malformed_intrinsics_file_is_one_data_error_naming_it(scene_copy, where):
    (scene_copy / "camera-intrinsics.txt").unlink()
    folder = scene_copy if where == "scene" else scene_copy.parent
    path = folder / "camera-intrinsics.txt"
    path.write_text("585 0 320\n0 585 240\n")
    with pytest.raises(DataError, match="expected a 3x3 matrix") as error:
        SevenScenes(scene_copy.parent, "room").frames("train")
    assert str(path) in str(error.value) and "\n" not in str(error.value)


def test_a_depth_map_of_another_size_is_one_data_error_naming_it(scene_copy):
    path = scene_copy / "seq-02" / "frame-000001.depth.png"
    assert cv2.imwrite(str(path), np.full((18, 24), 1500, dtype=np.uint16))
    frame = next(f for f in load_sevenscenes(scene_copy, None, "train") if f.depth_path == path)
    with pytest.raises(DataError, match="depth map is 24x18, expected 48x36") as error:
        read_frame_depth(frame)
    assert str(path) in str(error.value)
