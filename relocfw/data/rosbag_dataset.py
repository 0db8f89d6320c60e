"""dataset=rosbag: a map from a robot's own recording (a ROS 1 or ROS 2 bag).

Images come from an image topic (sensor_msgs/Image or CompressedImage); poses from a
pose topic (geometry_msgs/PoseStamped, nav_msgs/Odometry, or /tf's transform from
`tf_parent` to `tf_child`) or from a TUM trajectory file beside the bag (what ORB-SLAM2
writes), each image taking the pose nearest its header stamp within
`max_time_difference` seconds; images with none are left out and counted in one note
line. The camera comes from a CameraInfo topic or `intrinsics`; depth from an optional
depth topic (16UC1 millimetres or 32FC1 metres, registered to the colour camera, e.g.
a RealSense's aligned_depth_to_color). Train and test are time ranges in seconds from
the bag's first message.

The bag is extracted once into the cache (relocfw.data.rosbag_cache) and read from
there with relocfw.data.tum's own trajectory reading and matching. The poses are taken
as the camera's: a pose topic of the robot's base gives base poses, which a network
can learn but refine=features (PnP on the camera) cannot use.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.values import Pose
from relocfw.data.depth import MILLIMETRES_PER_METRE
from relocfw.data.frames import Frame
from relocfw.data.intrinsics import INTRINSICS_FILE, image_size, read_camera_for_images
from relocfw.data.on_error import OnError
from relocfw.data.options import metric_option
from relocfw.data.rosbag_cache import POSES_FILE, BagTopics, bag_summary, extracted_bag
from relocfw.data.rosbag_source import TF_MESSAGE
from relocfw.data.tum import associate, depth_paths, read_image_list, read_trajectory

UNITS_NOTE = "positions are in the bag's poses' own units (dataset.metric=false), not metres"
# Unmatched images named in the note before "...".
NAMED_UNMATCHED = 5


def time_ranges(value: object, key: str) -> list[tuple[float, float]] | None:
    """`[[t0, t1], ...]` seconds from the bag start as pairs, None where the key is not
    set (null), or a ConfigError naming key."""
    if value is None:
        return None
    pairs: list[tuple[float, float]] = []
    try:
        for pair in value or []:  # type: ignore[union-attr]
            start, end = (float(v) for v in pair)
            pairs.append((start, end))
    except (TypeError, ValueError):
        pairs = []
    if not pairs or any(not start < end for start, end in pairs):
        raise ConfigError(
            f"{key} must be time ranges [[t0, t1], ...] in seconds from the bag's start, "
            f"each t0 < t1; got {value!r}"
        )
    return pairs


def overlap(a: Sequence[tuple[float, float]], b: Sequence[tuple[float, float]]) -> bool:
    return any(s1 < e2 and s2 < e1 for s1, e1 in a for s2, e2 in b)


def within(seconds: np.ndarray, ranges: Sequence[tuple[float, float]]) -> np.ndarray:
    """Which times fall in any range [start, end): the end is left out, so ranges that
    meet ([[0, 60]] and [[60, 90]]) share no frame."""
    inside = np.zeros(len(seconds), dtype=bool)
    for start, end in ranges:
        inside |= (seconds >= start) & (seconds < end)
    return inside


def intrinsics_option(value: object) -> tuple[float, float, float, float] | None:
    """`dataset.intrinsics` [fx, fy, cx, cy] checked, or None where it is not set."""
    if value is None:
        return None
    try:
        fx, fy, cx, cy = (float(v) for v in value)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ConfigError(f"dataset.intrinsics must be [fx, fy, cx, cy], got {value!r}") from None
    if not (fx > 0 and fy > 0):
        raise ConfigError(f"dataset.intrinsics: focal lengths must be > 0, got {value!r}")
    return fx, fy, cx, cy


class RosbagDataset:
    """A ROS 1 / ROS 2 bag as a dataset (see the module).

    Args:
        bag: the `.bag` file, or the ROS 2 bag folder, `.db3` or `.mcap`.
        image_topic: the colour images.
        train_time: [[t0, t1], ...] seconds from the bag's start (t0 <= t < t1): the
            map's images; None: every image outside test_time.
        test_time: the same for the query images; must not overlap train_time. None:
            no test frames (the whole recording, or train_time, is the map, and a run
            scores nothing).
        pose_topic: PoseStamped, Odometry or tf2_msgs/TFMessage (/tf) topic.
        tf_parent, tf_child: the frames of the /tf transform taken as the camera pose.
        trajectory: a TUM trajectory file (relative to the bag's folder) instead.
        camera_info_topic: sensor_msgs/CameraInfo whose first K is the camera.
        intrinsics: [fx, fy, cx, cy] instead (wins over the topic).
        depth_topic: registered depth images (16UC1 mm, 32FC1 m).
        max_time_difference: seconds between an image and its pose at most.
        on_error: "fail" or "skip" (undecodable messages left out and listed).
        metric: whether the poses are metres; False makes reports say model units.
        cache_dir: where the extraction is kept (relocfw's cache_dir).
        quiet: no progress bars.
    """

    metric: bool = True
    units_note: str = ""

    def __init__(
        self,
        bag: str | None = None,
        image_topic: str | None = None,
        train_time: object = None,
        test_time: object = None,
        pose_topic: str | None = None,
        tf_parent: str = "map",
        tf_child: str = "camera",
        trajectory: str | None = None,
        camera_info_topic: str | None = None,
        intrinsics: object = None,
        depth_topic: str | None = None,
        max_time_difference: float = 0.02,
        on_error: str = "fail",
        metric: bool = True,
        cache_dir: str | Path = "~/.cache/relocfw",
        quiet: bool = False,
    ) -> None:
        self.metric = metric_option(metric)
        self.units_note = "" if self.metric else UNITS_NOTE
        if not bag:
            raise ConfigError("dataset.bag is not set: pass dataset.bag=FILE.bag (or a ROS 2 bag)")
        if not image_topic:
            raise ConfigError("dataset.image_topic is not set, e.g. /camera/color/image_raw")
        if bool(pose_topic) == bool(trajectory):
            raise ConfigError(
                "give the poses one way: dataset.pose_topic=TOPIC (PoseStamped, Odometry, "
                "/tf) or dataset.trajectory=FILE (TUM format, beside the bag)"
            )
        if not float(max_time_difference) > 0:
            raise ConfigError(f"dataset.max_time_difference must be > 0, got {max_time_difference}")
        self.ranges = {
            "train": time_ranges(train_time, "dataset.train_time"),
            "test": time_ranges(test_time, "dataset.test_time"),
        }
        train, test = self.ranges["train"], self.ranges["test"]
        if train is not None and test is not None and overlap(train, test):
            raise ConfigError("dataset.train_time and dataset.test_time overlap")
        # No test_time: no test frames by design, not an empty split by mistake.
        self.has_test_split = test is not None
        self.intrinsics = intrinsics_option(intrinsics)
        self.bag = Path(bag).expanduser()
        self.trajectory = self.bag.parent / trajectory if trajectory else None
        self.topics = BagTopics(
            image_topic, pose_topic or None, tf_parent, tf_child, camera_info_topic, depth_topic
        )
        self.max_time_difference = float(max_time_difference)
        self.on_error = OnError(on_error)
        self.cache_dir = Path(cache_dir).expanduser()
        self.quiet = quiet
        self.unmatched = 0
        self.posed: tuple[list[Frame], np.ndarray] | None = None

    def frames(self, split: str) -> list[Frame]:
        """The split's posed frames: those in its time ranges; for "train" without
        train_time, every one outside test_time; for "test" without test_time, none."""
        ranges = self.ranges[split]
        if split == "test" and ranges is None:
            return []
        frames, seconds = self.posed_frames()
        if ranges is None:
            inside = ~within(seconds, self.ranges["test"] or [])
        else:
            inside = within(seconds, ranges)
        return [frame for frame, keep in zip(frames, inside, strict=True) if keep]

    def split_source(self, split: str) -> str:
        """What picks the split's frames, for messages: its time ranges in the bag."""
        ranges = self.ranges[split]
        if ranges is None and split == "test":
            return "dataset.test_time is not set"
        if ranges is None:
            return f"dataset.train_time is not set (every image of {self.bag} outside test_time)"
        return f"dataset.{split}_time={[list(r) for r in ranges]} in {self.bag}"

    def posed_frames(self) -> tuple[list[Frame], np.ndarray]:
        """Every image with a pose, and its seconds from the bag's start (read once)."""
        if self.posed is None:
            self.posed = self.load()
        return self.posed

    def load(self) -> tuple[list[Frame], np.ndarray]:
        folder = extracted_bag(self.bag, self.topics, self.cache_dir, self.on_error, self.quiet)
        summary = bag_summary(folder)
        for problem in summary.get("skipped", []):
            self.on_error.handle(DataError(problem))
        images = read_image_list(folder / "rgb.txt", self.on_error)
        if not images:
            raise DataError(f"{self.bag}: no images on {self.topics.image_topic}")
        stamps, poses = self.poses(folder, summary)
        image_stamps = np.array([t for t, _ in images])
        matches = associate(image_stamps, stamps, self.max_time_difference)
        self.note_unmatched([name for (_, name), m in zip(images, matches, strict=True) if m < 0])
        kept = np.flatnonzero(matches >= 0)
        paths = [folder / images[i][1] for i in kept]
        camera = self.camera(folder, paths)
        depths = depth_paths(folder, image_stamps[kept], self.on_error)
        frames = [
            Frame(
                f"{self.bag.stem}/{Path(images[i][1]).stem}",
                path,
                poses[matches[i]],
                camera=camera,
                depth_path=depth,
                depth_units_per_metre=MILLIMETRES_PER_METRE,
            )
            for i, path, depth in zip(kept, paths, depths, strict=True)
        ]
        # To the microsecond: seconds of 1.7e9 as float64 are 2e-7 s apart, so a frame at
        # exactly a range's end would otherwise fall either side of it.
        seconds = np.round(image_stamps[kept] - summary["start_ns"] / 1e9, 6)
        return frames, seconds

    def poses(self, folder: Path, summary: dict) -> tuple[np.ndarray, list[Pose]]:
        """Timestamps and poses from the trajectory file, or from the pose topic."""
        if self.trajectory is not None:
            return read_trajectory(self.trajectory, self.on_error)
        path = folder / POSES_FILE
        if not path.read_text().strip():
            tf = summary["kinds"].get(self.topics.pose_topic) == TF_MESSAGE
            frames = f" from {self.topics.tf_parent} to {self.topics.tf_child}" if tf else ""
            raise DataError(f"{self.bag}: no poses on {self.topics.pose_topic}{frames}")
        return read_trajectory(path, self.on_error)

    def camera(self, folder: Path, images: Sequence[Path]) -> PinholeCamera | None:
        """dataset.intrinsics, else the CameraInfo topic's K, else none (no guess)."""
        if not images:
            return None
        if self.intrinsics is not None:
            width, height = image_size(images)
            return PinholeCamera(*self.intrinsics, width, height)
        if (folder / INTRINSICS_FILE).is_file():
            return read_camera_for_images(folder / INTRINSICS_FILE, images)
        return None

    def note_unmatched(self, names: list[str]) -> None:
        """One line on stderr: how many images had no pose close enough, and which."""
        self.unmatched = len(names)
        if not names:
            return
        stamps = [Path(n).stem for n in names[:NAMED_UNMATCHED]]
        more = ", ..." if len(names) > NAMED_UNMATCHED else ""
        print(
            f"note: {self.bag}: {len(names)} {'image' if len(names) == 1 else 'images'} on "
            f"{self.topics.image_topic} with no pose within {self.max_time_difference:g} s "
            f"(dataset.max_time_difference), left out: {', '.join(stamps)}{more}",
            file=sys.stderr,
        )
