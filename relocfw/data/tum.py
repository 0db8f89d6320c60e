"""TUM RGB-D and ORB-SLAM2 trajectories: `timestamp tx ty tz qx qy qz qw` (w LAST).

Images come from `rgb.txt` (`timestamp filename`) and get the pose of the nearest
trajectory timestamp within `max_time_difference` seconds; images with no pose that
close are left out and counted (TUM records images at 30 Hz, poses at other rates).

Each frame also gets a camera and, where the sequence has one, a depth map:
    camera      `camera-intrinsics.txt` in the sequence folder (7-Scenes' format: K,
                sized like the first image), else TUM's documented intrinsics of the
                sensor the folder is named after (freiburg1, freiburg2, freiburg3),
                else the ROS default (525, 525, 319.5, 239.5), all for 640 x 480.
                Either fallback prints one note on stderr naming the folder and the
                values, since a camera of one's own is rarely either of them.
                freiburg1 and freiburg2 images also have lens distortion that these
                pinhole values leave out, as TUM's own tools do.
    depth_path  the `depth.txt` entry (`timestamp filename`) nearest the image's
                timestamp within DEPTH_TIME_DIFFERENCE; TUM's depth PNGs are registered
                to the colour camera and hold 5000 units per metre (not millimetres).
                `dataset.depth_units_per_metre` says otherwise for another recorder
                (1000 for a millimetre PNG, as a RealSense writes); the value is
                carried as `Frame.depth_units_per_metre`.

Positions are metres only when every lap's trajectory is metric and in one world
frame (TUM's motion-capture ground truth is; monocular ORB-SLAM2's is neither: its
scale is arbitrary and each run has its own frame). `dataset.metric: false` says the
positions are not metres, as COLMAP's option does: reports name model units and leave
out the metre bands, and refine=features refuses depth maps (relocfw.report.units).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import checked_quaternion
from relocfw.core.values import Pose
from relocfw.data.depth import TUM_UNITS_PER_METRE
from relocfw.data.frames import Frame
from relocfw.data.intrinsics import INTRINSICS_FILE, note_default_camera, read_camera_for_images
from relocfw.data.on_error import OnError
from relocfw.data.options import depth_units_option, metric_option
from relocfw.data.text import data_lines, numbers

# TUM RGB-D's documented colour-camera intrinsics by sensor (the "file formats" page
# of the dataset), all for 640 x 480 images.
TUM_CAMERAS = {
    "freiburg1": PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480),
    "freiburg2": PinholeCamera(520.9, 521.0, 325.1, 249.7, 640, 480),
    "freiburg3": PinholeCamera(535.4, 539.2, 320.1, 247.6, 640, 480),
}
# The Kinect's ROS default, which TUM recommends when the sensor is unknown.
ROS_DEFAULT_CAMERA = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
SENSOR_NAME = re.compile(r"freiburg[123]", re.IGNORECASE)
# As TUM's associate.py: colour and depth are taken 1/30 s apart at most.
DEPTH_TIME_DIFFERENCE = 0.02
# What reports say first when dataset.metric is false (relocfw.report.units.unit_of).
UNITS_NOTE = "positions are in the trajectory's own units (dataset.metric=false), not metres"


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


def sequence_camera(folder: Path, images: Sequence[Path]) -> PinholeCamera:
    """The camera of a sequence: its intrinsics file, else its sensor's, else ROS's.

    A fallback prints one note on stderr (note_default_camera): wrong intrinsics do
    not fail, they only make refine=features' poses worse, so they must not be silent.

    Args:
        folder: the sequence folder; its name (e.g. rgbd_dataset_freiburg1_xyz) names
            the sensor.
        images: the colour images, in order (the first that decodes sizes a file's K).

    Raises:
        DataError: naming the intrinsics file when it is malformed.
    """
    path = folder / INTRINSICS_FILE
    if path.is_file():
        return read_camera_for_images(path, images)
    sensor = SENSOR_NAME.search(folder.name)
    if sensor:
        name = sensor.group().lower()
        note_default_camera(folder, TUM_CAMERAS[name], f"TUM's {name} intrinsics")
        return TUM_CAMERAS[name]
    note_default_camera(folder, ROS_DEFAULT_CAMERA, "the ROS default intrinsics")
    return ROS_DEFAULT_CAMERA


def depth_paths(
    folder: Path, image_stamps: np.ndarray, on_error: OnError | None = None
) -> list[Path | None]:
    """For each image timestamp, the depth map of `depth.txt` nearest it, or None.

    Args:
        folder: the sequence folder.
        image_stamps: [N] the colour images' timestamps in seconds.
        on_error: what to do with a bad depth.txt line (default: fail).

    Returns:
        N paths (as listed, not checked to exist: read_depth names a missing one), None
        where no depth map is within DEPTH_TIME_DIFFERENCE or there is no depth.txt.
    """
    path = folder / "depth.txt"
    entries = read_image_list(path, on_error) if path.is_file() else []
    if not entries:
        return [None] * len(image_stamps)
    order = np.argsort([t for t, _ in entries], kind="stable")
    stamps = np.array([entries[i][0] for i in order])
    matches = associate(np.asarray(image_stamps, dtype=np.float64), stamps, DEPTH_TIME_DIFFERENCE)
    return [folder / entries[order[m]][1] if m >= 0 else None for m in matches]


def load_tum_sequence(
    folder: Path,
    trajectory: str,
    max_time_difference: float,
    on_error: OnError | None = None,
    depth_units_per_metre: float = TUM_UNITS_PER_METRE,
) -> tuple[list[Frame], int]:
    """Frames of one recording, and how many images had no pose close enough.

    Each frame carries the sequence's camera and its depth map where depth.txt has
    one close in time, with `depth_units_per_metre` (see the module's docstring).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"sequence folder not found: {folder}")
    stamps, poses = read_trajectory(folder / trajectory, on_error)
    images = read_image_list(folder / "rgb.txt", on_error)
    if not images:
        raise DataError(f"{folder / 'rgb.txt'}: lists no images")
    image_stamps = np.array([t for t, _ in images])
    matches = associate(image_stamps, stamps, max_time_difference)
    posed = [(name, m) for (_, name), m in zip(images, matches, strict=True) if m >= 0]
    if not posed:
        return [], int(np.sum(matches < 0))
    camera = sequence_camera(folder, [folder / name for name, _ in posed])
    depths = depth_paths(folder, image_stamps[matches >= 0], on_error)
    frames = [
        Frame(
            f"{folder.name}/{Path(name).stem}",
            folder / name,
            poses[m],
            camera=camera,
            depth_path=depth,
            depth_units_per_metre=depth_units_per_metre,
        )
        for (name, m), depth in zip(posed, depths, strict=True)
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
        depth_units_per_metre: what one metre is stored as in the depth PNGs: 5000
            (TUM RGB-D's recorder), 1000 (millimetres, e.g. a RealSense).
        metric: whether the trajectories are metres in one world frame across laps;
            False (e.g. monocular ORB-SLAM2) makes reports say model units.

    Attributes:
        metric: read by relocfw.report.units.unit_of, as COLMAP's.
        units_note: one line for the reports of a non-metric run; "" when metric.
    """

    metric: bool = True
    units_note: str = ""

    def __init__(
        self,
        root: str,
        train: Sequence[str],
        test: Sequence[str],
        trajectory: str = "groundtruth.txt",
        max_time_difference: float = 0.02,
        on_error: str = "fail",
        depth_units_per_metre: float = TUM_UNITS_PER_METRE,
        metric: bool = True,
    ) -> None:
        # Options first, so a bad one is named whatever the folder holds.
        self.depth_units_per_metre = depth_units_option(depth_units_per_metre)
        self.metric = metric_option(metric)
        self.units_note = "" if self.metric else UNITS_NOTE
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
                self.root / sequence,
                self.trajectory,
                self.max_time_difference,
                self.on_error,
                self.depth_units_per_metre,
            )
            frames += found
            self.unmatched += unmatched
        return frames

    def split_source(self, split: str) -> str:
        """What lists the split's frames, for messages: its sequence folders."""
        return f"dataset.{split}={self.splits[split]} in {self.root}"
