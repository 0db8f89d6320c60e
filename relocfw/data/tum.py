"""TUM RGB-D and ORB-SLAM2 trajectories: `timestamp tx ty tz qx qy qz qw` (w LAST).

Images come from `rgb.txt` (`timestamp filename`) and get the pose of the nearest
trajectory timestamp within `max_time_difference` seconds; images with no pose that
close are left out and counted (TUM records images at 30 Hz, poses at other rates).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import checked_quaternion
from relocfw.core.values import Pose
from relocfw.data.frames import Frame
from relocfw.data.on_error import OnError
from relocfw.data.text import data_lines, numbers


def tum_quaternion_to_relocfw(qx: float, qy: float, qz: float, qw: float) -> list[float]:
    """TUM writes w last; relocfw keeps w first."""
    return [qw, qx, qy, qz]


def read_trajectory(path: Path, on_error: OnError | None = None) -> tuple[np.ndarray, list[Pose]]:
    """Timestamps (sorted) and camera-to-world poses of a TUM-format trajectory."""
    on_error = on_error or OnError()
    stamps: list[float] = []
    poses: list[Pose] = []
    seen: dict[float, str] = {}
    for source, fields in data_lines(path):
        try:
            t, x, y, z, qx, qy, qz, qw = numbers(fields, source, 8)
            if t in seen:
                raise DataError(f"{source}: duplicate timestamp {fields[0]} (first at {seen[t]})")
            quaternion = checked_quaternion(tum_quaternion_to_relocfw(qx, qy, qz, qw), source)
        except DataError as error:
            on_error.handle(error)
            continue
        seen[t] = source
        stamps.append(t)
        poses.append(Pose([x, y, z], quaternion))
    if not poses:
        raise DataError(f"{path}: no poses")
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps)[order], [poses[i] for i in order]


def read_image_list(path: Path, on_error: OnError | None = None) -> list[tuple[float, str]]:
    """(timestamp, relative file name) pairs of a TUM rgb.txt."""
    on_error = on_error or OnError()
    entries = []
    for source, fields in data_lines(path):
        try:
            if len(fields) != 2:
                raise DataError(f"{source}: expected 'timestamp filename', found {fields}")
            entries.append((numbers(fields[:1], source, 1)[0], fields[1]))
        except DataError as error:
            on_error.handle(error)
    return entries


def associate(
    image_stamps: np.ndarray, pose_stamps: np.ndarray, max_difference: float
) -> np.ndarray:
    """Index of the nearest pose for each image, or -1 when none is close enough."""
    right = np.clip(np.searchsorted(pose_stamps, image_stamps), 0, len(pose_stamps) - 1)
    left = np.clip(right - 1, 0, len(pose_stamps) - 1)
    pick = np.where(
        np.abs(pose_stamps[left] - image_stamps) <= np.abs(pose_stamps[right] - image_stamps),
        left,
        right,
    )
    close = np.abs(pose_stamps[pick] - image_stamps) <= max_difference
    return np.where(close, pick, -1)


def load_tum_sequence(
    folder: Path,
    trajectory: str,
    max_time_difference: float,
    on_error: OnError | None = None,
) -> tuple[list[Frame], int]:
    """Frames of one recording, and how many images had no pose close enough."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"sequence folder not found: {folder}")
    stamps, poses = read_trajectory(folder / trajectory, on_error)
    images = read_image_list(folder / "rgb.txt", on_error)
    if not images:
        raise DataError(f"{folder / 'rgb.txt'}: lists no images")
    matches = associate(np.array([t for t, _ in images]), stamps, max_time_difference)
    frames = [
        Frame(f"{folder.name}/{Path(name).stem}", folder / name, poses[m])
        for (_, name), m in zip(images, matches, strict=True)
        if m >= 0
    ]
    return frames, int(np.sum(matches < 0))


class TumDataset:
    """TUM RGB-D / ORB-SLAM2 recordings; each split is a list of sequence folders.

    Args:
        root: folder holding the sequence folders.
        train: sequence folders (laps) to map, e.g. [lap1, lap2].
        test: sequence folders to relocalize, e.g. [lap3].
        trajectory: pose file in each folder: groundtruth.txt, CameraTrajectory.txt
            or KeyFrameTrajectory.txt.
        max_time_difference: seconds between an image and its pose at most.
        on_error: "fail" or "skip" (bad lines left out and listed).
    """

    def __init__(
        self,
        root: str,
        train: Sequence[str],
        test: Sequence[str],
        trajectory: str = "groundtruth.txt",
        max_time_difference: float = 0.02,
        on_error: str = "fail",
    ) -> None:
        if root is None or not Path(root).expanduser().is_dir():
            raise DataError(f"dataset.root: folder not found: {root}")
        if not train or not test:
            raise ConfigError("dataset.train and dataset.test must each name sequence folders")
        if not float(max_time_difference) > 0:
            raise ConfigError(f"dataset.max_time_difference must be > 0, got {max_time_difference}")
        self.root = Path(root).expanduser()
        self.splits = {"train": list(train), "test": list(test)}
        self.trajectory = trajectory
        self.max_time_difference = float(max_time_difference)
        self.on_error = OnError(on_error)
        self.unmatched = 0

    def frames(self, split: str) -> list[Frame]:
        frames: list[Frame] = []
        for sequence in self.splits[split]:
            found, unmatched = load_tum_sequence(
                self.root / sequence, self.trajectory, self.max_time_difference, self.on_error
            )
            frames += found
            self.unmatched += unmatched
        return frames
