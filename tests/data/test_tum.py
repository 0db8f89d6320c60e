"""TUM RGB-D sequences give each frame a camera (by sensor, or a file) and its depth map."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.data.depth import read_frame_depth
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.data.tum import ROS_DEFAULT_CAMERA, TumDataset
from tests.data.formats import write_tum


@pytest.fixture
def tum_root(tiny_scene, tmp_path):
    """lap1 and lap2 (train) and lap3 (test) with depth, from the tiny synthetic scene."""
    write_tum(tiny_scene, tmp_path, depth=True)
    return tmp_path


def renamed(root, lap: str, name: str) -> str:
    shutil.move(root / lap, root / name)
    return name


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("rgbd_dataset_freiburg1_xyz", (517.3, 516.5, 318.6, 255.3)),
        ("rgbd_dataset_freiburg2_desk", (520.9, 521.0, 325.1, 249.7)),
        ("rgbd_dataset_Freiburg3_long_office_household", (535.4, 539.2, 320.1, 247.6)),
        ("lap3", (525.0, 525.0, 319.5, 239.5)),  # no sensor in the name: ROS's default
    ],
)
def test_the_camera_of_the_sensor_the_sequence_is_named_after(tum_root, name, expected):
    test = renamed(tum_root, "lap3", name)
    frames = TumDataset(str(tum_root), ["lap1"], [test]).frames("test")
    assert {f.camera for f in frames} == {PinholeCamera(*expected, 640, 480)}


def test_an_intrinsics_file_in_the_sequence_overrides_the_sensor(tum_root):
    test = renamed(tum_root, "lap3", "rgbd_dataset_freiburg1_xyz")
    (tum_root / test / "camera-intrinsics.txt").write_text("40 0 23.5\n0 41 17.5\n0 0 1\n")
    dataset = TumDataset(str(tum_root), ["lap1"], [test])
    # K from the file, the size from the first image (the scene's 48 x 36).
    assert {f.camera for f in dataset.frames("test")} == {PinholeCamera(40, 41, 23.5, 17.5, 48, 36)}
    assert {f.camera for f in dataset.frames("train")} == {ROS_DEFAULT_CAMERA}


def with_scene_camera(root, lap: str) -> None:
    """The tiny scene's 48 x 36 camera for a lap, so its depth maps fit the camera."""
    (root / lap / "camera-intrinsics.txt").write_text("43.875 0 23.5\n0 43.875 17.5\n0 0 1\n")


def test_depth_is_carried_at_5000_per_metre(tiny_scene, tum_root):
    with_scene_camera(tum_root, "lap3")
    frames = TumDataset(str(tum_root), ["lap1", "lap2"], ["lap3"]).frames("test")
    scene = load_sevenscenes(tiny_scene, None, "test")
    for frame, original in zip(frames, scene, strict=True):
        assert frame.depth_units_per_metre == 5000
        assert frame.depth_path.parent == tum_root / "lap3" / "depth"
        # The same metres as the scene's millimetre maps (which hold 1/5 the values).
        assert np.allclose(read_frame_depth(frame), read_frame_depth(original), atol=1e-6)


def test_depth_is_the_nearest_within_20_ms_or_none(tum_root):
    # lap3's depth stamps are 4 ms after its images (33 ms apart): move frame 1's
    # 25 ms earlier, 21 ms before the image, and drop frame 2's line.
    depth_txt = tum_root / "lap3" / "depth.txt"
    lines = depth_txt.read_text().splitlines()
    stamp, name = lines[2].split()
    lines[2] = f"{float(stamp) - 0.025:.6f} {name}"
    del lines[3]
    depth_txt.write_text("\n".join(reversed(lines)) + "\n")  # any order
    frames = TumDataset(str(tum_root), ["lap1"], ["lap3"]).frames("test")
    found = [None if f.depth_path is None else f.depth_path.name for f in frames]
    stamps = [f.image_path.stem for f in frames]
    assert found == [
        f"{float(stamps[0]) + 0.004:.6f}.png",
        None,
        None,
        f"{float(stamps[3]) + 0.004:.6f}.png",
    ]


def test_a_sequence_without_depth_txt_has_no_depth(tum_root):
    (tum_root / "lap1" / "depth.txt").unlink()
    frames = TumDataset(str(tum_root), ["lap1"], ["lap3"]).frames("train")
    assert frames and all(f.depth_path is None for f in frames)


def test_a_depth_map_of_another_size_than_the_camera_is_one_data_error(tum_root):
    # No intrinsics file and no sensor name: the ROS default's 640 x 480, but the
    # maps are the scene's 48 x 36.
    frame = TumDataset(str(tum_root), ["lap1"], ["lap3"]).frames("test")[0]
    with pytest.raises(DataError, match="depth map is 48x36, expected 640x480") as error:
        read_frame_depth(frame)
    assert str(frame.depth_path) in str(error.value) and "\n" not in str(error.value)


def test_a_malformed_intrinsics_file_is_one_data_error_naming_it(tum_root):
    path = tum_root / "lap3" / "camera-intrinsics.txt"
    path.write_text("40 0 23.5\n0 41 17.5\n0 0 2\n")
    with pytest.raises(DataError, match="bottom row must be 0 0 1") as error:
        TumDataset(str(tum_root), ["lap1"], ["lap3"]).frames("test")
    assert str(error.value).startswith(f"{path}:3: ")
