"""What every dataset yields: image files with their camera-to-world poses."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.core.geometry import mean_quaternion
from relocfw.core.imaging import read_rgb
from relocfw.core.observations import PointObservations
from relocfw.core.progress import Progress
from relocfw.core.values import Pose
from relocfw.data.on_error import OnError


@dataclass(frozen=True)
class Frame:
    """One image of a dataset, where the camera was, and what else the dataset knows of it.

    Attributes:
        name: unique within the dataset, e.g. "seq-01/frame-000000".
        image_path: the colour image (any size, colour or grey, PNG or JPEG).
        pose: camera-to-world, position in metres (model units for an unaligned
            COLMAP model), unit quaternion w first.
        camera: the pinhole intrinsics of the image at its full resolution (OpenCV's
            convention, relocfw.core.camera), or None where the dataset gives none or
            its camera has lens distortion (see relocfw.data.colmap_cameras.pinhole_of).
        depth_path: a depth map of the frame: a single-channel 16-bit PNG of z along
            the optical axis of the depth sensor in `depth_units_per_metre` units per
            metre, 0 = no reading; None where the dataset has none. Read it with
            relocfw.data.depth.read_frame_depth.
        depth_units_per_metre: the depth map's scale: 1000 (millimetres) for 7-Scenes
            and the synthetic scene, 5000 for TUM RGB-D.
        observations: the 3-D points a reconstruction saw in the image, with their
            pixels (a COLMAP model's points3D: relocfw.data.colmap_points); None
            where the dataset has none.
        depth_camera: the depth sensor's intrinsics at the depth map's resolution, or
            None: the depth map is registered to the colour image and is read pixel
            for pixel with it (the synthetic scene, TUM RGB-D). 7-Scenes' raw Kinect
            depth has its own camera (relocfw.data.sevenscenes).
        depth_to_colour: [4, 4] rigid transform from depth-camera coordinates to
            colour-camera coordinates (relocfw.core.rigid.checked_rigid), used with
            `depth_camera`; None: the identity.
        pose_to_colour: [4, 4] rigid transform from the coordinates of the sensor
            that `pose` describes to the colour camera's (relocfw.core.sensor_poses);
            None: `pose` is the colour camera's. 7-Scenes' poses are its depth
            sensor's, so there it is `depth_to_colour`.
    """

    name: str
    image_path: Path
    pose: Pose
    # Optional and last, so the three-argument Frame(name, path, pose) of every
    # dataset without cameras (Cambridge, the plain folder, tests) stays valid.
    camera: PinholeCamera | None = None
    depth_path: Path | None = None
    depth_units_per_metre: float = 1000.0
    observations: PointObservations | None = None
    depth_camera: PinholeCamera | None = None
    depth_to_colour: np.ndarray | None = None
    pose_to_colour: np.ndarray | None = None


def claim_frame_name(claimed: dict[str, Path], name: str, image: Path, source: str) -> None:
    """Record that `image` is frame `name`; refuse a second image with the same name.

    Frame names drop the extension, so `a.png` and `a.jpg` in one folder would become
    one frame name, and every later step (the map, the answers, the summaries) would
    silently hold one of them twice or mix them up.

    Raises:
        DataError: naming both files, where another image already has the name.
    """
    other = claimed.setdefault(name, image)
    if other != image:
        raise DataError(
            f"{source}: {image} and {other} would both be frame {name!r} (a frame is "
            "named by its path without the extension); rename or remove one of them"
        )


def positions_of(frames: Sequence[Frame]) -> np.ndarray:
    return np.stack([f.pose.position for f in frames])


def quaternions_of(frames: Sequence[Frame]) -> np.ndarray:
    return np.stack([f.pose.quaternion for f in frames])


def mean_pose(frames: Sequence[Frame]) -> Pose:
    """Average training position and rotation: the no-information answer."""
    return Pose(positions_of(frames).mean(axis=0), mean_quaternion(quaternions_of(frames)))


def read_images(
    frames: Sequence[Frame], label: str = "loading images", quiet: bool = False, threads: int = 4
) -> list[np.ndarray]:
    """Decode all frames' images; OpenCV releases the GIL, so threads decode in parallel."""
    return read_good_images(frames, OnError(), label, quiet, threads)[1]


def read_good_images(
    frames: Sequence[Frame],
    on_error: OnError,
    label: str = "loading images",
    quiet: bool = False,
    threads: int = 4,
) -> tuple[list[Frame], list[np.ndarray]]:
    """Frames whose image decodes, with the images; the others go to `on_error`."""

    def attempt(frame: Frame) -> np.ndarray | DataError:
        try:
            return read_rgb(frame.image_path)
        except DataError as error:
            return error

    progress = Progress(len(frames), label, quiet=quiet)
    kept, images = [], []
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for frame, image in zip(frames, pool.map(attempt, frames), strict=True):
            progress.advance()
            if isinstance(image, DataError):
                on_error.handle(image)
                continue
            kept.append(frame)
            images.append(image)
    progress.close()
    return kept, images
