"""Writers of small datasets in each supported format, following the format's own rules.

Written independently of the loaders: TUM puts w last, Cambridge stores the
world-to-camera rotation, the plain folder names its columns in a header.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from relocfw.core.geometry import matrix_to_quaternion, quaternion_to_matrix
from relocfw.data.sevenscenes import load_sevenscenes


def scene_frames(scene: Path, split: str):
    return load_sevenscenes(scene, None, split)


TUM_DEPTH_PER_MILLIMETRE = 5  # TUM's depth PNGs: 5000 per metre


def write_tum(scene: Path, root: Path, depth: bool = False) -> dict[str, list]:
    """One TUM folder per lap: rgb.txt (30 Hz stamps) and groundtruth.txt (w last).

    With `depth`, also depth.txt and depth/STAMP.png as the Kinect recorder writes
    them: stamps 4 ms after the colour image's, 16-bit values of 5000 per metre (the
    scene's millimetres times 5).
    """
    laps = {
        "lap1": scene_frames(scene, "train")[:8],
        "lap2": scene_frames(scene, "train")[8:],
        "lap3": scene_frames(scene, "test"),
    }
    for name, frames in laps.items():
        folder = root / name
        (folder / "rgb").mkdir(parents=True)
        if depth:
            (folder / "depth").mkdir()
        rgb, truth = ["# timestamp filename"], ["# timestamp tx ty tz qx qy qz qw"]
        depth_lines = ["# timestamp filename"]
        for i, frame in enumerate(frames):
            stamp = 1000.0 + i / 30.0
            shutil.copy(frame.image_path, folder / "rgb" / f"{stamp:.6f}.png")
            rgb.append(f"{stamp:.6f} rgb/{stamp:.6f}.png")
            if depth:
                millimetres = cv2.imread(str(frame.depth_path), cv2.IMREAD_UNCHANGED)
                depth_name = f"depth/{stamp + 0.004:.6f}.png"
                units = millimetres * np.uint16(TUM_DEPTH_PER_MILLIMETRE)
                assert cv2.imwrite(str(folder / depth_name), units)
                depth_lines.append(f"{stamp + 0.004:.6f} {depth_name}")
            w, x, y, z = frame.pose.quaternion
            # Pose stamps 5 ms off the image's, as a mocap clock would be.
            truth.append(
                " ".join(f"{v:.9f}" for v in (stamp + 0.005, *frame.pose.position, x, y, z, w))
            )
        (folder / "rgb.txt").write_text("\n".join(rgb) + "\n")
        (folder / "groundtruth.txt").write_text("\n".join(truth) + "\n")
        if depth:
            (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    return laps


def write_cambridge(scene: Path, root: Path) -> dict[str, list]:
    """dataset_train.txt / dataset_test.txt: path, camera centre, world-to-camera quaternion."""
    folder = root / "Room"
    splits = {"train": scene_frames(scene, "train"), "test": scene_frames(scene, "test")}
    for split, frames in splits.items():
        lines = ["Visual Landmark Dataset V1", "ImageFile, Camera Position [X Y Z W P Q R]", ""]
        for frame in frames:
            name = f"seq{1 if split == 'train' else 2}/{frame.image_path.name}"
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(frame.image_path, folder / name)
            camera_to_world = quaternion_to_matrix(frame.pose.quaternion)
            world_to_camera = matrix_to_quaternion(camera_to_world.T)
            lines.append(
                " ".join([name, *(f"{v:.9f}" for v in (*frame.pose.position, *world_to_camera))])
            )
        (folder / f"dataset_{split}.txt").write_text("\n".join(lines) + "\n")
    return splits


def write_folder(scene: Path, root: Path) -> dict[str, list]:
    """train.csv / test.csv with the columns in an unusual order."""
    splits = {"train": scene_frames(scene, "train"), "test": scene_frames(scene, "test")}
    (root / "images").mkdir(parents=True)
    for split, frames in splits.items():
        lines = ["qz,qy,qx,qw,z,y,x,image"]
        for i, frame in enumerate(frames):
            name = f"images/{split}_{i:03d}.png"
            shutil.copy(frame.image_path, root / name)
            w, x, y, z = frame.pose.quaternion
            px, py, pz = frame.pose.position
            lines.append(",".join([*(f"{v:.9f}" for v in (z, y, x, w, pz, py, px)), name]))
        (root / f"{split}.csv").write_text("\n".join(lines) + "\n")
    return splits


def assert_same_poses(loaded, expected):
    assert len(loaded) == len(expected)
    for a, b in zip(loaded, expected, strict=True):
        assert np.allclose(a.pose.position, b.pose.position, atol=1e-7)
        assert np.allclose(a.pose.quaternion, b.pose.quaternion, atol=1e-7)
