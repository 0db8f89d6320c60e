"""What every dataset yields: image files with their camera-to-world poses."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocfw.core.errors import DataError
from relocfw.core.geometry import mean_quaternion
from relocfw.core.imaging import read_rgb
from relocfw.core.progress import Progress
from relocfw.core.values import Pose
from relocfw.data.on_error import OnError


@dataclass(frozen=True)
class Frame:
    """One image of a dataset and where the camera was."""

    name: str  # unique within the dataset, e.g. "seq-01/frame-000000"
    image_path: Path
    pose: Pose


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
