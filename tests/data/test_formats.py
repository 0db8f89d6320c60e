from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from relocfw.core.errors import DataError
from relocfw.core.geometry import checked_quaternion, quaternion_to_matrix
from relocfw.core.imaging import Strip, read_rgb
from relocfw.core.values import Pose
from relocfw.data.cambridge import CambridgeLandmarks
from relocfw.data.folder import PoseFolder
from relocfw.data.on_error import OnError
from relocfw.data.tum import TumDataset, associate, read_trajectory
from relocfw.model.training import TrainingImages
from tests.data.formats import assert_same_poses, write_cambridge, write_folder, write_tum


def test_tum_round_trip(tiny_scene, tmp_path):
    laps = write_tum(tiny_scene, tmp_path)
    dataset = TumDataset(str(tmp_path), train=["lap1", "lap2"], test=["lap3"])
    assert_same_poses(dataset.frames("train"), laps["lap1"] + laps["lap2"])
    test = dataset.frames("test")
    assert_same_poses(test, laps["lap3"])
    assert read_rgb(test[0].image_path).shape == (36, 48, 3)
    assert dataset.unmatched == 0


def test_tum_w_is_last(tmp_path):
    path = tmp_path / "CameraTrajectory.txt"
    # 90 degrees about z, written x y z w.
    path.write_text("1.0 0 0 0 0 0 0.7071067811865476 0.7071067811865476\n")
    _, poses = read_trajectory(path)
    assert np.allclose(poses[0].quaternion, [0.7071067811865476, 0, 0, 0.7071067811865476])
    assert np.allclose(quaternion_to_matrix(poses[0].quaternion) @ [1, 0, 0], [0, 1, 0])


def test_association_by_nearest_timestamp_within_tolerance():
    poses = np.array([0.0, 1.0, 2.0])
    assert list(associate(np.array([0.01, 0.98, 1.6, 2.02]), poses, 0.05)) == [0, 1, -1, 2]


def test_cambridge_stores_world_to_camera(tiny_scene, tmp_path):
    splits = write_cambridge(tiny_scene, tmp_path)
    dataset = CambridgeLandmarks(str(tmp_path), "Room")
    assert_same_poses(dataset.frames("train"), splits["train"])
    assert_same_poses(dataset.frames("test"), splits["test"])
    # Read the file's own numbers: they map a world point into the camera frame.
    line = (tmp_path / "Room" / "dataset_test.txt").read_text().splitlines()[3].split()
    centre, world_to_camera = np.array(line[1:4], float), np.array(line[4:8], float)
    frame = dataset.frames("test")[0]
    point = np.array([1.0, 2.0, 1.5])
    in_camera = quaternion_to_matrix(world_to_camera) @ (point - centre)
    back = quaternion_to_matrix(frame.pose.quaternion) @ in_camera + frame.pose.position
    assert np.allclose(back, point)


def test_plain_folder_reads_columns_by_name(tiny_scene, tmp_path):
    splits = write_folder(tiny_scene, tmp_path)
    dataset = PoseFolder(str(tmp_path))
    assert_same_poses(dataset.frames("train"), splits["train"])
    assert_same_poses(dataset.frames("test"), splits["test"])


def test_unnormalised_quaternion_rule():
    with pytest.warns(UserWarning, match="norm 2"):
        assert np.allclose(checked_quaternion([2, 0, 0, 0], "f:1"), [1, 0, 0, 0])
    assert np.allclose(checked_quaternion([1.0000001, 0, 0, 0], "f:1"), [1, 0, 0, 0])
    with pytest.raises(DataError, match="f:2: quaternion has \\(near\\) zero norm"):
        checked_quaternion([0, 0, 0, 1e-9], "f:2")


def test_grey_portrait_and_small_images(tmp_path):
    grey = tmp_path / "grey.jpg"
    cv2.imwrite(str(grey), np.random.default_rng(0).integers(0, 255, (120, 80), dtype=np.uint8))
    image = read_rgb(grey)
    assert image.shape == (120, 80, 3)
    strip = Strip(image, 64)  # portrait: the square slides along y
    assert strip.pixels.shape[1:] == (96, 64)
    small = Strip(np.zeros((20, 30, 3), np.uint8), 64)  # smaller than the input: upscaled
    assert small.pixels.shape[1:] == (64, 96)


def test_skip_policy_collects_messages(tiny_scene, tmp_path):
    write_tum(tiny_scene, tmp_path)
    path = tmp_path / "lap1" / "groundtruth.txt"
    lines = path.read_text().splitlines()
    lines[2] = "1000.0 nan 0 0 0 0 0 1"
    path.write_text("\n".join(lines) + "\n")
    dataset = TumDataset(str(tmp_path), ["lap1"], ["lap3"], on_error="skip")
    frames = dataset.frames("train")
    assert len(dataset.on_error.skipped) == 1 and "groundtruth.txt:3" in dataset.on_error.skipped[0]
    assert len(frames) == 7 and dataset.unmatched == 1  # its image now has no pose
    with pytest.raises(Exception, match="on_error"):
        OnError("ignore")


def flip_every_other_quaternion(trajectory: Path) -> None:
    """Negate (qx, qy, qz, qw) on every other line: the same rotations, as SLAM writes them."""
    lines = trajectory.read_text().splitlines()
    out, poses = [], 0
    for line in lines:
        if line.startswith("#"):
            out.append(line)
            continue
        values = line.split()
        if poses % 2:
            values[4:8] = [f"{-float(v):.9f}" for v in values[4:8]]
        poses += 1
        out.append(" ".join(values))
    trajectory.write_text("\n".join(out) + "\n")


def test_tum_quaternion_sign_flips_give_the_same_training_targets(tiny_scene, tmp_path):
    write_tum(tiny_scene, tmp_path / "plain")
    write_tum(tiny_scene, tmp_path / "flipped")
    for lap in ("lap1", "lap2"):
        flip_every_other_quaternion(tmp_path / "flipped" / lap / "groundtruth.txt")
    targets = []
    for name in ("plain", "flipped"):
        frames = TumDataset(str(tmp_path / name), ["lap1", "lap2"], ["lap3"]).frames("train")
        data = TrainingImages([None] * len(frames), [f.pose for f in frames], 32)
        targets.append((data.positions, data.quaternions))
    flipped_lines = (tmp_path / "flipped" / "lap1" / "groundtruth.txt").read_text().splitlines()
    assert float(flipped_lines[2].split()[-1]) < 0  # the file really holds w < 0 lines
    assert torch.equal(targets[0][0], targets[1][0])
    assert torch.equal(targets[0][1], targets[1][1])
    assert bool((targets[1][1][:, 0] > 0).all())


def test_every_pose_is_put_on_the_w_positive_hemisphere():
    q = np.array([-0.5, 0.5, -0.5, 0.5])
    assert np.array_equal(Pose([0, 0, 0], q).quaternion, -q)
    assert np.array_equal(Pose([0, 0, 0], -q).quaternion, -q)
    # w = 0 (a half turn): the first non-zero component decides.
    assert np.array_equal(Pose([0, 0, 0], [0.0, 0.0, -1.0, 0.0]).quaternion, [0, 0, 1, 0])
