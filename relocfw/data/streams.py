"""Frames to localize from what `localize.images` names: image files (a file, a folder,
a glob), a video file or a ROS bag, all as one iterator of StreamFrame.

Frames are decoded one at a time as they are asked for, so memory stays flat however
long the stream, and a frame that cannot be decoded is a frame with `error` set rather
than an exception: the caller decides whether that stops the run (`on_error=fail`) or
is listed and skipped (`on_error=skip`).

A bag is read by `relocfw.data.rosbag_source`, imported only when a bag is named, so
relocfw works without the `rosbags` library (`pip install relocfw[robot]`).
"""

from __future__ import annotations

import glob
import re
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import MAX_ASPECT, check_aspect, read_rgb
from relocfw.data.stream_frame import StreamFrame
from relocfw.data.video_source import is_video, video_frame_count, video_frames

__all__ = [
    "StreamFrame",
    "count_frames",
    "file_frames",
    "find_images",
    "open_frames",
    "source_kind",
    "timestamp_of",
    "within_aspect",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
TIMESTAMP_NAME = re.compile(r"\d+(\.\d+)?")
ROS2_BAG_SUFFIXES = (".db3", ".mcap")
INSTALL_HINT = "reading a ROS bag needs the rosbags library: pip install relocfw[robot]"


def is_bag(path: Path) -> bool:
    """A ROS bag: a `.bag` file (ROS 1), a `.db3` or `.mcap` file, or a folder holding
    `metadata.yaml` (ROS 2)."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.is_file() and path.suffix.lower() in (".bag", *ROS2_BAG_SUFFIXES)


def source_kind(spec: str) -> str:
    """What `spec` names: "bag", "video" or "files" (a file, folder or glob of images)."""
    path = Path(spec).expanduser()
    if is_bag(path):
        return "bag"
    if is_video(path):
        return "video"
    return "files"


def open_frames(
    spec: str, topic: str | None = None, max_aspect: float = MAX_ASPECT
) -> Iterator[StreamFrame]:
    """The frames `spec` names, in order, each decoded when it is reached.

    Image files come in today's order (a folder's or glob's sorted by name) with
    today's timestamps (`timestamp_of`); a video's and a bag's frames in stream order
    with their own timestamps. What is wrong with the spec itself is raised here,
    before any frame is read.

    Args:
        spec: a file, folder or glob of images, a video file, or a ROS bag.
        topic: the bag's image topic (required for a bag, refused for anything else).
        max_aspect: an image file thinner than this (query.max_aspect) is an error
            frame, refused on its header before it is decoded. A video's and a bag's
            frames have no such header: `within_aspect` checks their pixels.

    Raises:
        ConfigError: naming localize.images when `spec` is empty, localize.topic when
            a bag is named without one (listing the bag's image topics) or a topic is
            given for images or a video; saying how to install rosbags for a bag
            without it.
        DataError: naming `spec` when it names no image, or only depth maps.
    """
    kind = source_kind(spec) if spec else "files"
    if topic and kind != "bag":
        raise ConfigError(
            f"localize.topic={topic} is for ROS bags; localize.images={spec} is "
            f"{'a video' if kind == 'video' else 'image files'}: leave localize.topic out"
        )
    path = Path(spec).expanduser()
    if kind == "video":
        return video_frames(path)
    if kind == "bag":
        return bag_source(path, topic)
    paths = find_images(spec)
    return file_frames(paths, max_aspect)


def count_frames(spec: str, topic: str | None = None) -> int | None:
    """How many frames `open_frames(spec, topic)` will give, for a progress bar; None
    when the source does not say (a video without a frame count)."""
    kind = source_kind(spec) if spec else "files"
    path = Path(spec).expanduser()
    if kind == "video":
        return video_frame_count(path)
    if kind == "bag":
        if not topic:
            return None
        bag = rosbag_module()
        with bag.Bag(path) as opened:
            return opened.topic(topic, bag.IMAGE_TYPES, "localize.topic").count
    return len(find_images(spec))


def rosbag_module() -> ModuleType:
    """relocfw.data.rosbag_source, imported on first use; a ConfigError saying how to
    install rosbags where it is missing."""
    try:
        from relocfw.data import rosbag_source
    except ModuleNotFoundError as error:
        if (error.name or "").split(".")[0] == "rosbags":
            raise ConfigError(INSTALL_HINT) from None
        raise
    return rosbag_source


def bag_source(path: Path, topic: str | None) -> Iterator[StreamFrame]:
    """The bag's frames on `topic`; without a topic, a ConfigError listing its image
    topics."""
    bag = rosbag_module()
    if not topic:
        topics = bag.image_topics(path)
        raise ConfigError(
            f"localize.topic is not set: localize.images={path} is a ROS bag; pass its "
            f"image topic, localize.topic=TOPIC (its image topics: {', '.join(topics) or 'none'})"
        )
    return bag.bag_frames(path, topic, "localize.topic")


def find_images(pattern: str) -> list[Path]:
    """Images named by a file, a folder (every image in it) or a glob pattern."""
    if not pattern:
        raise ConfigError(
            "localize.images is not set: pass localize.images=FILE, localize.images=DIR, "
            "localize.images='DIR/*.png', a video (localize.images=run.mp4) or a ROS bag "
            "(localize.images=run.bag localize.topic=/camera/image_raw)"
        )
    path = Path(pattern).expanduser()
    if path.is_dir():
        found = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    elif path.is_file():
        found = [path]
    else:
        found = sorted(Path(p) for p in glob.glob(str(path)))
    if not found:
        raise DataError(f"localize.images={pattern}: no image files found")
    # A 7-Scenes or synthetic sequence keeps 16-bit depth maps beside its colour
    # images; read as colour they would be localized as nonsense, not refused.
    depth = [p for p in found if p.name.lower().endswith(".depth.png")]
    if depth:
        raise DataError(
            f"localize.images={pattern}: {len(depth)} of the {len(found)} files are depth "
            f"maps ({depth[0].name}, ...); name the colour images, e.g. "
            f"localize.images='{depth[0].parent}/*.color.png'"
        )
    return found


def timestamp_of(path: Path, position: int) -> str:
    """The file name's number when it is one (TUM names images by time), else its index.

    Only plain decimals count (digits, one optional fraction): `float` would also take
    names such as "nan", "inf" or "1_000", which TUM tools cannot read back.
    """
    return path.stem if TIMESTAMP_NAME.fullmatch(path.stem) else str(position)


def file_frames(paths: list[Path], max_aspect: float = MAX_ASPECT) -> Iterator[StreamFrame]:
    """The images in order, each read when reached; one that cannot be read (or is
    thinner than `max_aspect`) is an error frame carrying read_rgb's message (which
    names the file)."""
    for position, path in enumerate(paths):
        stamp = timestamp_of(path, position)
        try:
            image = read_rgb(path, max_aspect, key="query.max_aspect")
        except DataError as error:
            yield StreamFrame(str(path), stamp, None, str(error))
            continue
        yield StreamFrame(str(path), stamp, image, None)


def within_aspect(frame: StreamFrame, max_aspect: float) -> StreamFrame:
    """`frame`, or an error frame naming it when its pixels are thinner than
    `max_aspect` (query.max_aspect): refused as a frame, so on_error=skip goes on."""
    if frame.image is None:
        return frame
    height, width = frame.image.shape[:2]
    try:
        check_aspect(width, height, f"{frame.name} is", max_aspect)
    except DataError as error:
        return StreamFrame(frame.name, frame.timestamp, None, str(error))
    return frame
