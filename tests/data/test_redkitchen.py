"""The real Red Kitchen recording (../shared/data, never copied in): near and far splits."""

from pathlib import Path

import numpy as np
import pytest

from relocfw.core.camera import PinholeCamera
from relocfw.data.depth import read_frame_depth
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import SEVENSCENES_DEPTH_TO_COLOUR, SevenScenes

REDKITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "7scenes-redkitchen"


@pytest.fixture
def redkitchen() -> Path:
    if not (REDKITCHEN / "redkitchen" / "TrainSplit.txt").is_file():
        pytest.skip(f"Red Kitchen frames not found at {REDKITCHEN}")
    return REDKITCHEN


def sequence_of(name: str) -> int:
    return int(name.split("seq-")[1][:2])


@pytest.mark.parametrize(
    "train, test, expected_train, expected_test",
    [
        (None, None, {1, 3, 5, 7}, {2, 4, 6}),  # near: the split files
        ([1, 2, 3, 4], [5, 6, 7], {1, 2, 3, 4}, {5, 6, 7}),  # far: later views
    ],
)
def test_near_and_far_splits_are_one_option_each(
    redkitchen, train, test, expected_train, expected_test
):
    scenes = SevenScenes(
        root=str(redkitchen), scene="redkitchen", train_sequences=train, test_sequences=test
    )
    train_frames, test_frames = scenes.frames("train"), scenes.frames("test")
    assert {sequence_of(f.name) for f in train_frames} == expected_train
    assert {sequence_of(f.name) for f in test_frames} == expected_test
    assert len(train_frames) == 100 * len(expected_train)
    assert len(test_frames) == 100 * len(expected_test)
    # KinectFusion camera-to-world poses in metres: the path spans about 2 m.
    positions = np.stack([f.pose.position for f in train_frames])
    assert 1.0 < np.ptp(positions, axis=0).max() < 4.0
    image = read_images(test_frames[:1], quiet=True)[0]
    assert image.shape == (480, 640, 3) and image.dtype == np.uint8


def test_frames_carry_the_kinect_camera_and_their_depth_maps(redkitchen):
    # camera-intrinsics.txt is at the dataset root, beside the scene folder.
    frames = SevenScenes(root=str(redkitchen), scene="redkitchen").frames("test")
    # The file is 7-Scenes' depth calibration (intrinsics_for=depth, the default); the
    # colour images get the nominal 525 camera and depth is registered to them.
    assert {f.depth_camera for f in frames} == {PinholeCamera(585.0, 585.0, 320.0, 240.0, 640, 480)}
    assert {f.camera for f in frames} == {PinholeCamera(525.0, 525.0, 320.0, 240.0, 640, 480)}
    assert all(f.depth_to_colour is SEVENSCENES_DEPTH_TO_COLOUR for f in frames)
    assert all(f.depth_path is not None and f.depth_path.is_file() for f in frames)
    assert frames[0].depth_path == frames[0].image_path.with_name("frame-000000.depth.png")
    depth = read_frame_depth(frames[0])
    assert depth.shape == (480, 640) and 0.5 < np.nanmedian(depth) < 4.0  # metres
