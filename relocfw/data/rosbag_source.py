"""Reading a robot's recording: ROS 1 `.bag` files and ROS 2 bags (folder, .db3, .mcap).

Read with `rosbags` (pure Python, no ROS install; the `relocfw[robot]` extra), imported
only here and only when a bag is opened, so relocfw works without it.

A bag is data from someone else, so it is read under the model files' trust rule:
rosbags can build Python types from the message definitions a bag carries (by
generating and executing code), so relocfw never does that. Messages are decoded with
rosbags' own built-in ROS 1 Noetic / ROS 2 Humble types, only for the few message types
relocfw reads (MESSAGE_TYPES), and a connection whose recorded type hash differs from
the standard one is refused rather than decoded by guess.

A bag whose container cannot be read (truncated, corrupt, not a bag) is one DataError
naming the file; one message that does not decode is that message's problem only
(`bag_frames` yields it as an error frame).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

from relocfw.core.errors import ConfigError, DataError
from relocfw.data.ros_images import COMPRESSED_IMAGE, colour_image
from relocfw.data.stream_frame import StreamFrame

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
POSE_TYPES = (POSE_STAMPED, ODOMETRY, TF_MESSAGE)
MESSAGE_TYPES = (*IMAGE_TYPES, CAMERA_INFO, *POSE_TYPES)
# rosbags' ROS 1 store lacks tf2_msgs/TFMessage; this is its standard definition (its
# MD5 is ROS's, 94810edda583a504dfda3829e70d7eec), written here, not taken from a bag.
ROS1_TF_MESSAGE = "geometry_msgs/TransformStamped[] transforms\n"
INSTALL_HINT = "reading ROS bags needs the rosbags library: pip install relocfw[robot]"


def rosbags_modules() -> Any:
    """The rosbags readers and type stores, imported on first use; a ConfigError
    saying how to install them where they are missing."""
    try:
        from rosbags import rosbag1, rosbag2, typesys
    except ImportError:
        raise ConfigError(INSTALL_HINT) from None
    return rosbag1, rosbag2, typesys


def is_ros1(path: Path) -> bool:
    """A ROS 1 bag is one `.bag` file; anything else is taken as a ROS 2 bag."""
    return path.suffix == ".bag" and not path.is_dir()


def standard_types(ros1: bool) -> Any:
    """rosbags' built-in type store of the ROS version (never the bag's definitions)."""
    _, _, typesys = rosbags_modules()
    if not ros1:
        return typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    store = typesys.get_typestore(typesys.Stores.ROS1_NOETIC)
    store.register(typesys.get_types_from_msg(ROS1_TF_MESSAGE, TF_MESSAGE))
    return store


@dataclass(frozen=True)
class Topic:
    """One topic of a bag: its message type and how many messages it holds."""

    name: str
    msgtype: str
    count: int


class Bag:
    """An open bag: its topics and the decoded messages of the types relocfw reads.

    Use as a context manager. Every failure of the container (opening, reading a chunk
    or a row) is a DataError naming the file; a message that does not decode comes out
    as its exception, for the caller to list.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path).expanduser()
        if not self.path.exists():
            raise DataError(f"bag not found: {self.path}")
        rosbag1, rosbag2, _ = rosbags_modules()
        self.ros1 = is_ros1(self.path)
        self.types = standard_types(self.ros1)
        try:
            self.reader = (rosbag1.Reader if self.ros1 else rosbag2.Reader)(self.path)
            self.reader.open()
        except Exception as error:  # rosbags, struct, sqlite3 and OS errors alike
            raise DataError(f"{self.path}: cannot read the bag ({describe(error)})") from None

    def __enter__(self) -> Bag:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        # Closing a damaged bag must not hide the first error.
        with contextlib.suppress(Exception):
            self.reader.close()

    @property
    def start_ns(self) -> int:
        """The bag time of its first message, in nanoseconds."""
        return int(self.reader.start_time)

    def topics(self) -> list[Topic]:
        counts: dict[str, Topic] = {}
        for connection in self.reader.connections:
            seen = counts.get(connection.topic)
            total = int(connection.msgcount) + (seen.count if seen else 0)
            counts[connection.topic] = Topic(connection.topic, connection.msgtype, total)
        return [counts[name] for name in sorted(counts)]

    def topic(self, name: str, accepted: Sequence[str], key: str) -> Topic:
        """The topic `name`, which must hold one of the `accepted` types.

        Raises:
            ConfigError: naming `key`, the bag and the topics it has of those types.
        """
        topics = {t.name: t for t in self.topics()}
        found = topics.get(name)
        if found is not None and found.msgtype in accepted:
            return found
        fitting = [t.name for t in topics.values() if t.msgtype in accepted]
        what = "no such topic" if found is None else f"it holds {found.msgtype}"
        kinds = ", ".join(a.replace("/msg/", "/") for a in accepted)
        raise ConfigError(
            f"{key}={name}: {what} in {self.path}; its topics of type {kinds}: "
            f"{', '.join(fitting) or 'none'}"
        )

    def messages(self, topics: Sequence[str]) -> Iterator[tuple[str, int, object]]:
        """(topic, bag time in ns, message or the exception decoding it) in bag order.

        Raises:
            DataError: naming the bag when a connection's type is not the standard one
                (its recorded hash differs) or the container cannot be read.
        """
        connections = [c for c in self.reader.connections if c.topic in topics]
        for connection in connections:
            self.check_standard(connection)
        decode = self.types.deserialize_ros1 if self.ros1 else self.types.deserialize_cdr
        stream = self.reader.messages(connections=connections)
        while True:
            try:
                item = next(stream, None)
            except Exception as error:
                raise DataError(f"{self.path}: cannot read the bag ({describe(error)})") from None
            if item is None:
                return
            connection, stamp, raw = item
            try:
                message: object = decode(raw, connection.msgtype)
            except Exception as error:  # one bad message: the caller lists it
                message = DataError(f"{connection.topic}: message does not decode ({error})")
            yield connection.topic, int(stamp), message

    def check_standard(self, connection: Any) -> None:
        """Refuse a connection whose type is not one relocfw reads or whose recorded
        hash is not the standard definition's (decoding it would be a guess)."""
        if connection.msgtype not in MESSAGE_TYPES:
            raise DataError(
                f"{self.path}: topic {connection.topic} holds {connection.msgtype}, "
                "which relocfw does not read"
            )
        digest = str(connection.digest or "")
        if self.ros1:
            standard = self.types.generate_msgdef(connection.msgtype)[1]
        elif digest.startswith("RIHS01_"):
            standard = self.types.hash_rihs01(connection.msgtype)
        else:
            return  # ROS 2 before Iron records no type hash: the name is all there is
        if digest and digest != standard:
            raise DataError(
                f"{self.path}: topic {connection.topic}: {connection.msgtype} recorded with "
                f"type hash {digest}, not the standard {standard}; relocfw reads only the "
                "standard message definitions"
            )


def describe(error: BaseException) -> str:
    """An exception as one short phrase: its type and message."""
    text = str(error).strip().splitlines()[0] if str(error).strip() else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def header_stamp(message: Any, bag_ns: int) -> int:
    """The message header's stamp in ns; the bag time where the stamp is zero (some
    drivers never fill it)."""
    stamp = message.header.stamp
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return ns if ns > 0 else bag_ns


def seconds_text(ns: int) -> str:
    """Nanoseconds as seconds with 9 decimals, exactly (no float rounding)."""
    sign = "-" if ns < 0 else ""
    whole, part = divmod(abs(ns), 1_000_000_000)
    return f"{sign}{whole}.{part:09d}"


def image_topics(path: str | Path) -> list[str]:
    """The bag's topics of sensor_msgs/Image or CompressedImage, sorted.

    Raises:
        DataError: naming the bag when it cannot be read.
        ConfigError: when rosbags is not installed.
    """
    with Bag(path) as bag:
        return [t.name for t in bag.topics() if t.msgtype in IMAGE_TYPES]


def bag_frames(path: Path, topic: str, key: str = "localize.topic") -> Iterator[StreamFrame]:
    """The colour images of one topic of a bag, in bag order, with their own timestamps.

    Each frame's timestamp is its header stamp (the bag time where the stamp is zero)
    as seconds with 9 decimals; its name is that timestamp (`<stamp>_<n>` for the n-th
    frame of a repeated stamp). A message that does not
    decode is a frame with `error` set and no image, so a stream goes on past it.

    Args:
        path: a ROS 1 `.bag`, or a ROS 2 bag folder, `.db3` or `.mcap`.
        topic: a topic of sensor_msgs/Image (rgb8, bgr8, mono8, rgba8, bgra8) or
            sensor_msgs/CompressedImage.
        key: the setting that named the topic, for messages.

    Raises:
        ConfigError: naming `key` and listing the bag's image topics where `topic` is
            not one of them; naming the topic where it holds depth; without rosbags.
        DataError: naming the bag where its container cannot be read.
    """
    bag = Bag(path)
    try:
        found = bag.topic(topic, IMAGE_TYPES, key)  # refused now, not at the first frame
    except Exception:
        bag.close()
        raise
    return topic_frames(bag, found)


def topic_frames(bag: Bag, topic: Topic) -> Iterator[StreamFrame]:
    """bag_frames' frames of an open bag's checked topic; the bag is closed at the end.

    A frame's name is its stamp; a later frame with a stamp already seen (a driver
    that repeats one) is named `<stamp>_<n>`, its n-th, so every answer names its own
    frame. Its timestamp stays the stamp.
    """
    seen: dict[str, int] = {}

    def named(stamp: str) -> str:
        seen[stamp] = seen.get(stamp, 0) + 1
        return stamp if seen[stamp] == 1 else f"{stamp}_{seen[stamp]}"

    with bag:
        for _, bag_ns, message in bag.messages([topic.name]):
            if isinstance(message, Exception):
                stamp = seconds_text(bag_ns)
                yield StreamFrame(named(stamp), stamp, None, str(message))
                continue
            stamp = seconds_text(header_stamp(message, bag_ns))
            try:
                image = colour_image(message, topic.msgtype, topic.name)
            except DataError as error:
                yield StreamFrame(named(stamp), stamp, None, str(error))
                continue
            yield StreamFrame(named(stamp), stamp, image, None)
