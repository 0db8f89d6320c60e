import re
import shutil

import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import pose_to_matrix
from relocfw.core.imaging import read_rgb
from relocfw.data.sevenscenes import SevenScenes, load_sevenscenes, read_pose_file, read_split


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
