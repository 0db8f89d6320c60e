"""The frames of a video file, decoded by OpenCV (its FFmpeg backend), with their own
timestamps.

A frame that fails to decode in the middle of a video (a damaged packet) is an error
frame, and the frames after it are still read: OpenCV's `grab` fails for that frame
and succeeds again for the next. The end of the video is where grabbing keeps
failing past the container's frame count; failed frames that the count covers are
error frames too (a damaged tail), those past it are not frames at all.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from relocfw.core.errors import DataError
from relocfw.data.stream_frame import StreamFrame

VIDEO_SUFFIXES = (
    ".mp4",
    ".m4v",
    ".avi",
    ".mkv",
    ".mov",
    ".webm",
    ".mpg",
    ".mpeg",
    ".wmv",
    ".flv",
    ".ts",
)
# Failed grabs in a row taken as the end of the video once past its frame count (a
# damaged stretch the count covers is read through, up to MAX_DAMAGED_RUN frames).
END_AFTER_FAILURES = 16
MAX_DAMAGED_RUN = 10_000


def is_video(path: Path) -> bool:
    """A video file: a file whose suffix is a video container's."""
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def open_video(path: Path) -> cv2.VideoCapture:
    """The opened capture, or one DataError naming the file."""
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise DataError(f"cannot open video {path} (not a video, or a codec OpenCV lacks)")
    return capture


def video_frame_count(path: Path) -> int | None:
    """The frame count the container announces; None where it gives none."""
    capture = open_video(path)
    try:
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        capture.release()
    return count if count > 0 else None


def seconds_of(milliseconds: float) -> str:
    """A time in ms as seconds with 9 decimals, as poses.txt writes it."""
    return f"{milliseconds / 1000.0:.9f}"


def video_frames(path: Path) -> Iterator[StreamFrame]:
    """Every frame of the video in order: named `VIDEO#INDEX`, timestamped with its
    presentation time (CAP_PROP_POS_MSEC) in seconds.

    Raises:
        DataError: naming the file when OpenCV cannot open it.
    """
    capture = open_video(path)
    return read_frames(capture, path)


def read_frames(capture: cv2.VideoCapture, path: Path) -> Iterator[StreamFrame]:
    """The frames of an opened capture (released when the iteration ends)."""
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    fps = float(capture.get(cv2.CAP_PROP_FPS))
    failed: list[int] = []  # frames whose grab failed since the last good one
    index = 0
    try:
        while len(failed) < END_AFTER_FAILURES or (index < count and len(failed) < MAX_DAMAGED_RUN):
            if not capture.grab():
                failed.append(index)
                index += 1
                continue
            for bad in failed:  # a later frame decoded: the failed ones were frames
                yield error_frame(path, bad, fps, "it does not decode")
            failed = []
            stamp = seconds_of(capture.get(cv2.CAP_PROP_POS_MSEC))
            ok, pixels = capture.retrieve()
            yield decoded_frame(path, index, stamp, pixels if ok else None)
            index += 1
        for bad in failed:
            if bad < count:  # the container says the frame exists: a damaged tail
                yield error_frame(path, bad, fps, f"it does not decode (of {count} frames)")
    finally:
        capture.release()


def decoded_frame(path: Path, index: int, stamp: str, pixels: np.ndarray | None) -> StreamFrame:
    """The frame as RGB, after checking it is 8-bit colour; an error frame if not."""
    name = f"{path}#{index}"
    if pixels is None:
        return StreamFrame(name, stamp, None, f"{name} (at {stamp} s): it does not decode")
    if pixels.dtype != np.uint8 or pixels.ndim != 3 or pixels.shape[2] != 3:
        return StreamFrame(
            name, stamp, None, f"{name}: decoded as {pixels.dtype} {pixels.shape}, not 8-bit colour"
        )
    return StreamFrame(name, stamp, np.ascontiguousarray(pixels[:, :, ::-1]), None)


def error_frame(path: Path, index: int, fps: float, why: str) -> StreamFrame:
    """A frame that could not be read; its time is estimated from the frame rate (the
    capture gives none for a frame it failed on)."""
    stamp = seconds_of(1000.0 * index / fps) if fps > 0 else ""
    when = f" (at about {stamp} s)" if stamp else ""
    return StreamFrame(f"{path}#{index}", stamp, None, f"{path}#{index}{when}: {why}")
