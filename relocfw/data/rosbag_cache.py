"""A bag's images, depth, camera and poses, extracted once into a TUM-layout folder.

Every later step of relocfw (decoding on demand, training, the structure cache keyed
by pixels) reads a Frame's image from a file, so a bag is turned into files once and
the rest of the pipeline is unchanged: `rgb.txt` + `rgb/<stamp>.png`, `depth.txt` +
`depth/<stamp>.png` (16-bit millimetres), `camera-intrinsics.txt` (the first
CameraInfo's K) and `poses.txt` (TUM format, w last), exactly what relocfw.data.tum
reads. PNG is lossless, so the pixels are the bag's (a CompressedImage's as decoded).

The folder is named by a hash of the bag's bytes and the topics read, so a second run
reads no bag, and an edited bag or another topic gets its own folder. It is written
into a staging folder and renamed into place, so an interrupted extraction is never
trusted; one a killed run left is removed by the next extraction into the same
cache (relocfw.core.atomic_files.remove_stale_folders). Every image of the topic is
extracted (not only those with a pose): then the pose options (tolerance, time
ranges, a trajectory file) can change without a re-read.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from relocfw.core.atomic_files import (
    publish_folder,
    release_folder,
    remove_stale_folders,
    staging_folder,
)
from relocfw.core.errors import DataError
from relocfw.core.progress import Progress
from relocfw.data.depth import write_depth
from relocfw.data.intrinsics import INTRINSICS_FILE
from relocfw.data.on_error import OnError
from relocfw.data.ros_images import colour_image, depth_image
from relocfw.data.rosbag_source import (
    CAMERA_INFO,
    IMAGE_TYPES,
    ODOMETRY,
    POSE_STAMPED,
    POSE_TYPES,
    TF_MESSAGE,
    Bag,
    header_stamp,
    rosbags_modules,
    seconds_text,
)

# Bump when the extracted folder's files change, so an older extraction is not reused.
EXTRACTION_VERSION = 1
POSES_FILE = "poses.txt"
HASH_BLOCK = 1 << 23
# How an extraction's staging folder is named (then a random part), beside its place.
STAGING_PREFIX = ".extracting-"


@dataclass(frozen=True)
class BagTopics:
    """What is read from a bag (each a dataset option of the same name)."""

    image_topic: str
    pose_topic: str | None = None
    tf_parent: str = "map"
    tf_child: str = "camera"
    camera_info_topic: str | None = None
    depth_topic: str | None = None


def bag_files(path: Path) -> list[Path]:
    """The files a bag is made of: the file, or every file of a ROS 2 bag folder."""
    if path.is_dir():
        return sorted(p for p in path.rglob("*") if p.is_file())
    return [path]


def bag_hash(path: Path, quiet: bool) -> str:
    """SHA-256 of the bag's bytes (and, for a folder, its file names)."""
    files = bag_files(path)
    digest = hashlib.sha256()
    blocks = sum(f.stat().st_size for f in files) // HASH_BLOCK + 1
    progress = Progress(blocks, "hashing bag", quiet)
    for file in files:
        digest.update(str(file.relative_to(path) if path.is_dir() else file.name).encode())
        with file.open("rb") as handle:
            while block := handle.read(HASH_BLOCK):
                digest.update(block)
                progress.advance()
    progress.close()
    return digest.hexdigest()


def extracted_bag(
    path: Path, topics: BagTopics, cache_dir: Path, on_error: OnError, quiet: bool = False
) -> Path:
    """The folder of the bag's extraction (see the module), made if it is not there.

    Messages that do not decode stop it under on_error=fail; under skip they are left
    out and recorded in bag.json's "skipped" (the caller hands them to on_error, for a
    fresh extraction and a reused one alike).

    Raises:
        DataError: naming the bag when it cannot be read.
        ConfigError: naming the option of a topic the bag lacks (listing its topics of
            the right type).
    """
    if not path.exists():
        raise DataError(f"dataset.bag: not found: {path}")
    rosbags_modules()  # without rosbags, say so before hashing a large bag
    key_text = json.dumps(
        {"bag": bag_hash(path, quiet), "topics": asdict(topics), "version": EXTRACTION_VERSION},
        sort_keys=True,
    )
    folder = cache_dir / "bags" / hashlib.sha256(key_text.encode()).hexdigest()[:16]
    if (folder / "bag.json").is_file():
        return folder
    folder.parent.mkdir(parents=True, exist_ok=True)
    # A killed extraction cannot clean up: its folder goes here, once its lock is free
    # (a live one, of another run, holds its lock and stays).
    remove_stale_folders(folder.parent, STAGING_PREFIX)
    staging, lock = staging_folder(folder.parent, STAGING_PREFIX)
    try:
        with Bag(path) as bag:
            summary = Extraction(bag, topics, staging, on_error).run(quiet)
        (staging / "bag.json").write_text(json.dumps({**summary, "key": key_text}, indent=2))
        publish_folder(staging, folder, "bag.json")
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        release_folder(lock)
    return folder


class Extraction:
    """One pass over the chosen topics of an open bag, writing the folder's files."""

    def __init__(self, bag: Bag, topics: BagTopics, folder: Path, on_error: OnError) -> None:
        self.bag, self.topics, self.folder, self.on_error = bag, topics, folder, on_error
        self.kinds: dict[str, str] = {}
        image = bag.topic(topics.image_topic, IMAGE_TYPES, "dataset.image_topic")
        self.kinds[image.name] = image.msgtype
        for name, types, key in (
            (topics.pose_topic, POSE_TYPES, "dataset.pose_topic"),
            (topics.camera_info_topic, (CAMERA_INFO,), "dataset.camera_info_topic"),
            (topics.depth_topic, ("sensor_msgs/msg/Image",), "dataset.depth_topic"),
        ):
            if name:
                self.kinds[name] = bag.topic(name, types, key).msgtype
        self.lines: dict[str, list[str]] = {"rgb": [], "depth": [], "poses": []}
        self.seen: dict[str, set[str]] = {"rgb": set(), "depth": set(), "poses": set()}
        self.skipped: list[str] = []
        self.camera: list[float] | None = None

    def run(self, quiet: bool) -> dict[str, Any]:
        total = sum(t.count for t in self.bag.topics() if t.name in self.kinds)
        progress = Progress(total, f"reading {self.bag.path.name}", quiet)
        for name in ("rgb", "depth"):
            (self.folder / name).mkdir()
        for topic, bag_ns, message in self.bag.messages(list(self.kinds)):
            progress.advance()
            try:
                if isinstance(message, DataError):
                    raise message
                self.take(topic, bag_ns, message)
            except DataError as error:
                # Under skip, kept in bag.json too: a reused extraction lists them again.
                problem = DataError(f"{self.bag.path}: {error}")
                if self.on_error.mode == "fail":
                    raise problem from None
                self.skipped.append(str(problem))
        progress.close()
        for name, lines in (("rgb.txt", "rgb"), ("depth.txt", "depth"), (POSES_FILE, "poses")):
            (self.folder / name).write_text("".join(self.lines[lines]))
        if self.camera is not None:
            k = np.asarray(self.camera, dtype=np.float64).reshape(3, 3)
            np.savetxt(self.folder / INTRINSICS_FILE, k, fmt="%.18e")
        return {
            "bag": str(self.bag.path),
            "start_ns": self.bag.start_ns,
            "topics": asdict(self.topics),
            "kinds": self.kinds,
            "images": len(self.lines["rgb"]),
            "poses": len(self.lines["poses"]),
            "skipped": self.skipped,
        }

    def take(self, topic: str, bag_ns: int, message: Any) -> None:
        """File one decoded message under what its topic is for."""
        if topic == self.topics.image_topic:
            stamp = self.claim("rgb", header_stamp(message, bag_ns), topic)
            rgb = colour_image(message, self.kinds[topic], topic)
            if not cv2.imwrite(str(self.folder / "rgb" / f"{stamp}.png"), rgb[:, :, ::-1]):
                raise DataError(f"cannot write {self.folder / 'rgb' / f'{stamp}.png'}")
            self.lines["rgb"].append(f"{stamp} rgb/{stamp}.png\n")
        elif topic == self.topics.depth_topic:
            stamp = self.claim("depth", header_stamp(message, bag_ns), topic)
            write_depth(self.folder / "depth" / f"{stamp}.png", depth_image(message, topic))
            self.lines["depth"].append(f"{stamp} depth/{stamp}.png\n")
        elif topic == self.topics.camera_info_topic:
            if self.camera is None:
                k = message.k if hasattr(message, "k") else message.K  # ROS 2 / ROS 1
                values = np.asarray(k, dtype=np.float64).reshape(-1)
                if values.size != 9:
                    raise DataError(f"{topic}: CameraInfo K has {values.size} values, not 9")
                self.camera = values.tolist()
        else:
            for stamp, position, rotation in self.poses(message, bag_ns):
                if seconds_text(stamp) in self.seen["poses"]:
                    continue  # /tf repeats a transform at one stamp: the first is kept
                self.seen["poses"].add(seconds_text(stamp))
                numbers = [position.x, position.y, position.z]
                numbers += [rotation.x, rotation.y, rotation.z, rotation.w]
                text = " ".join(repr(float(v)) for v in numbers)
                self.lines["poses"].append(f"{seconds_text(stamp)} {text}\n")

    def claim(self, kind: str, stamp_ns: int, topic: str) -> str:
        """The stamp as a file name, refusing a second message with the same stamp."""
        stamp = seconds_text(stamp_ns)
        if stamp in self.seen[kind]:
            raise DataError(f"{topic}: a second message stamped {stamp}; left out")
        self.seen[kind].add(stamp)
        return stamp

    def poses(self, message: Any, bag_ns: int) -> list[tuple[int, Any, Any]]:
        """(stamp ns, position, orientation) of a pose message: a PoseStamped, an
        Odometry's pose, or each /tf transform from tf_parent to tf_child."""
        kind = self.kinds[self.topics.pose_topic or ""]
        if kind == POSE_STAMPED:
            pose = message.pose
            return [(header_stamp(message, bag_ns), pose.position, pose.orientation)]
        if kind == ODOMETRY:
            pose = message.pose.pose
            return [(header_stamp(message, bag_ns), pose.position, pose.orientation)]
        assert kind == TF_MESSAGE
        parent, child = self.topics.tf_parent.lstrip("/"), self.topics.tf_child.lstrip("/")
        return [
            (header_stamp(t, bag_ns), t.transform.translation, t.transform.rotation)
            for t in message.transforms
            if t.header.frame_id.lstrip("/") == parent and t.child_frame_id.lstrip("/") == child
        ]


def bag_summary(folder: Path) -> dict[str, Any]:
    """What extracted_bag recorded of the bag (start time, counts, topics)."""
    try:
        return json.loads((folder / "bag.json").read_text())
    except (OSError, ValueError) as error:
        raise DataError(f"{folder}: damaged bag extraction; delete the folder ({error})") from None
