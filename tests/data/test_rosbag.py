"""ROS bags: frames of an image topic (bag_frames) and dataset=rosbag, on small ROS 1
and ROS 2 bags written here with rosbags itself, good and bad."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.data import rosbag_source
from relocfw.data.depth import read_frame_depth
from relocfw.data.rosbag_dataset import RosbagDataset
from relocfw.data.rosbag_source import bag_frames, image_topics, standard_types

pytest.importorskip("rosbags")

START = 1_700_000_000 * 10**9  # bag time of the first message, ns
STEP = 100_000_000  # 10 Hz


def ns(seconds: float) -> int:
    return START + round(seconds * 1e9)


class BagWriter:
    """Writes messages built from rosbags' standard types into a ROS 1 or ROS 2 bag."""

    def __init__(self, path: Path, ros1: bool, mcap: bool = False) -> None:
        from rosbags import rosbag1, rosbag2

        self.ros1 = ros1
        self.types = standard_types(ros1)
        storage = rosbag2.StoragePlugin.MCAP if mcap else rosbag2.StoragePlugin.SQLITE3
        self.writer = (
            rosbag1.Writer(path)
            if ros1
            else rosbag2.Writer(path, version=9, storage_plugin=storage)
        )
        self.writer.open()
        self.connections: dict[str, object] = {}

    def __getattr__(self, name: str):  # message classes by short name: self.Image(...)
        for full in self.types.types:
            if full.endswith(f"/{name}"):
                return self.types.types[full]
        raise AttributeError(name)

    def header(self, stamp: int, frame: str = "camera"):
        time = self.Time(sec=stamp // 10**9, nanosec=stamp % 10**9)
        extra = {"seq": 0} if self.ros1 else {}
        return self.Header(**extra, stamp=time, frame_id=frame)

    def write(self, topic: str, message, bag_time: int) -> None:
        msgtype = message.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=self.types
            )
        serialize = self.types.serialize_ros1 if self.ros1 else self.types.serialize_cdr
        self.writer.write(self.connections[topic], bag_time, bytes(serialize(message, msgtype)))

    def image(self, topic: str, stamp: int, rgb: np.ndarray, encoding="rgb8", bag_time=None):
        pixels = {"rgb8": rgb, "bgr8": rgb[:, :, ::-1], "mono8": rgb[:, :, :1]}[encoding]
        self.write(topic, self.raw_image(stamp, pixels, encoding), bag_time or stamp)

    def raw_image(self, stamp: int, values: np.ndarray, encoding: str):
        """A sensor_msgs/Image of `values` ([H, W] or [H, W, C]) as its bytes in memory."""
        height, width = values.shape[:2]
        return self.Image(
            header=self.header(stamp),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=values[0].nbytes,
            data=np.ascontiguousarray(values).view(np.uint8).reshape(-1),
        )

    def compressed(self, topic: str, stamp: int, rgb: np.ndarray) -> None:
        data = cv2.imencode(".png", rgb[:, :, ::-1])[1].reshape(-1)
        message = self.CompressedImage(header=self.header(stamp), format="png", data=data)
        self.write(topic, message, stamp)

    def depth(self, topic: str, stamp: int, metres: np.ndarray, encoding="16UC1") -> None:
        values = (metres * 1000).astype("<u2") if encoding == "16UC1" else metres.astype("<f4")
        self.write(topic, self.raw_image(stamp, values, encoding), stamp)

    def pose(self, topic: str, stamp: int, position, quaternion_xyzw) -> None:
        point = self.Point(x=position[0], y=position[1], z=position[2])
        x, y, z, w = quaternion_xyzw
        pose = self.Pose(position=point, orientation=self.Quaternion(x=x, y=y, z=z, w=w))
        self.write(topic, self.PoseStamped(header=self.header(stamp, "map"), pose=pose), stamp)

    def tf(self, topic: str, stamp: int, parent: str, child: str, position) -> None:
        translation = self.Vector3(x=position[0], y=position[1], z=position[2])
        rotation = self.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
        moved = self.TransformStamped(
            header=self.header(stamp, parent),
            child_frame_id=child,
            transform=self.Transform(translation=translation, rotation=rotation),
        )
        self.write(topic, self.TFMessage(transforms=[moved]), stamp)

    def camera_info(self, topic: str, stamp: int, k: list[float], width: int, height: int):
        keys = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        arrays = [np.zeros(5), np.array(k, float), np.eye(3).reshape(-1), np.zeros(12)]
        roi = self.RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        message = self.CameraInfo(
            header=self.header(stamp),
            height=height,
            width=width,
            distortion_model="plumb_bob",
            **dict(zip(keys, arrays, strict=True)),
            binning_x=0,
            binning_y=0,
            roi=roi,
        )
        self.write(topic, message, stamp)

    def close(self) -> None:
        self.writer.close()


def texture(seed: int, width: int = 16, height: int = 12) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


def bag_path(tmp_path: Path, ros1: bool, name: str = "run") -> Path:
    return tmp_path / (f"{name}.bag" if ros1 else name)


@pytest.fixture(params=[True, False], ids=["ros1", "ros2"])
def ros1(request) -> bool:
    return request.param


def test_bag_frames_read_image_and_compressed_pixels_at_header_stamps(tmp_path, ros1):
    path = bag_path(tmp_path, ros1)
    bag = BagWriter(path, ros1)
    stamps = [ns(0.0), ns(0.1), ns(0.2)]
    for i, (stamp, encoding) in enumerate(zip(stamps, ["rgb8", "bgr8", "rgb8"], strict=True)):
        bag.image("/cam/image", stamp + 5, texture(i), encoding, bag_time=stamp + 1000)
        bag.compressed("/cam/compressed", stamp, texture(10 + i))
    bag.image("/cam/image", 0, texture(3), bag_time=ns(0.3))  # no stamp: the bag time
    bag.image("/cam/grey", stamps[0], texture(4), "mono8")
    bag.close()

    frames = list(bag_frames(path, "/cam/image"))
    assert [f.timestamp for f in frames] == [
        "1700000000.000000005",
        "1700000000.100000005",
        "1700000000.200000005",
        "1700000000.300000000",
    ]
    for i, frame in enumerate(frames):
        assert frame.error is None and frame.image.dtype == np.uint8
        np.testing.assert_array_equal(frame.image, texture(i))
    compressed = list(bag_frames(path, "/cam/compressed"))
    assert [f.timestamp for f in compressed] == [f"1700000000.{i}00000000" for i in range(3)]
    for i, frame in enumerate(compressed):
        np.testing.assert_array_equal(frame.image, texture(10 + i))
    (grey,) = bag_frames(path, "/cam/grey")
    np.testing.assert_array_equal(grey.image, np.repeat(texture(4)[:, :, :1], 3, axis=2))
    assert image_topics(path) == ["/cam/compressed", "/cam/grey", "/cam/image"]
    with rosbag_source.Bag(path) as opened:
        assert opened.topic("/cam/image", rosbag_source.IMAGE_TYPES, "k").count == 4


def test_a_ros2_mcap_bag_reads_from_its_folder_or_its_file(tmp_path):
    path = tmp_path / "run"
    bag = BagWriter(path, False, mcap=True)
    bag.compressed("/cam", ns(0), texture(0))
    bag.close()
    for source in (path, next(path.glob("*.mcap"))):
        (frame,) = bag_frames(source, "/cam")
        np.testing.assert_array_equal(frame.image, texture(0))


def test_a_message_that_does_not_decode_is_an_error_frame(tmp_path):
    path = bag_path(tmp_path, False)
    bag = BagWriter(path, False)
    bag.image("/cam", ns(0), texture(0))
    short = bag.Image(
        header=bag.header(ns(0.1)),
        height=12,
        width=16,
        encoding="rgb8",
        is_bigendian=0,
        step=48,
        data=np.zeros(10, np.uint8),
    )
    bag.write("/cam", short, ns(0.1))
    bag.image("/cam", ns(0.2), texture(2))
    bag.close()
    frames = list(bag_frames(path, "/cam"))
    assert [f.image is None for f in frames] == [False, True, False]
    assert "/cam" in frames[1].error and "too few" in frames[1].error


def test_a_wrong_topic_is_one_config_error_listing_the_image_topics(tmp_path, ros1):
    path = bag_path(tmp_path, ros1)
    bag = BagWriter(path, ros1)
    bag.image("/camera/color/image_raw", ns(0), texture(0))
    bag.compressed("/camera/color/image_raw/compressed", ns(0), texture(0))
    bag.pose("/pose", ns(0), [0, 0, 0], [0, 0, 0, 1])
    bag.close()
    with pytest.raises(ConfigError) as refused:
        bag_frames(path, "/camera/rgb")  # at the call, before any frame is read
    message = str(refused.value)
    assert "\n" not in message and "localize.topic=/camera/rgb" in message
    assert "/camera/color/image_raw, /camera/color/image_raw/compressed" in message
    with pytest.raises(ConfigError, match="/pose: it holds geometry_msgs"):
        list(bag_frames(path, "/pose"))


def test_a_depth_topic_is_refused_as_colour_naming_it(tmp_path):
    path = bag_path(tmp_path, True)
    bag = BagWriter(path, True)
    bag.depth("/camera/depth", ns(0), np.full((12, 16), 1.5))
    bag.close()
    with pytest.raises(ConfigError, match="/camera/depth holds 16UC1 depth"):
        list(bag_frames(path, "/camera/depth"))


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_a_truncated_bag_is_one_data_error_naming_it(tmp_path, ros1):
    path = bag_path(tmp_path, ros1)
    bag = BagWriter(path, ros1)
    for i in range(20):
        bag.image("/cam", ns(i / 10), texture(i, 64, 48))
    bag.close()
    file = path if ros1 else next(path.glob("*.db3"))
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    with pytest.raises(DataError, match=str(path)) as refused:
        list(bag_frames(path, "/cam"))
    assert "\n" not in str(refused.value)


def test_without_rosbags_a_bag_is_one_config_error_saying_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags", None)
    with pytest.raises(ConfigError, match=r"pip install relocfw\[robot\]"):
        rosbag_source.rosbags_modules()


def write_recording(path: Path, ros1: bool, poses_on: str | None = "/pose") -> list[np.ndarray]:
    """Ten images at 10 Hz; PoseStamped poses at the image times (+3 ms) but for
    images 4 and 7; camera info and 16UC1 depth."""
    bag = BagWriter(path, ros1)
    bag.camera_info("/cam/info", ns(0), [20.0, 0, 7.5, 0, 21.0, 5.5, 0, 0, 1], 16, 12)
    for i in range(10):
        bag.image("/cam/image", ns(i / 10), texture(i))
        bag.depth("/cam/depth", ns(i / 10), np.full((12, 16), 1.0 + i / 10))
        if poses_on and i not in (4, 7):
            bag.pose(poses_on, ns(i / 10 + 0.003), [i, 2 * i, 0.5], [0, 0, 0, 1])
    bag.close()
    return [texture(i) for i in range(10)]


def rosbag_dataset(path: Path, tmp_path: Path, **options) -> RosbagDataset:
    settings = dict(
        bag=str(path),
        image_topic="/cam/image",
        train_time=[[0, 0.6]],  # meets test_time: the frame at 0.6 s is a test frame
        test_time=[[0.6, 2]],
        cache_dir=tmp_path / "cache",
        quiet=True,
    )
    return RosbagDataset(**{**settings, **options})


def test_dataset_poses_from_a_pose_topic_match_by_time_and_list_the_unmatched(
    tmp_path, ros1, capsys
):
    path = bag_path(tmp_path, ros1)
    images = write_recording(path, ros1)
    dataset = rosbag_dataset(
        path, tmp_path, pose_topic="/pose", camera_info_topic="/cam/info", depth_topic="/cam/depth"
    )
    train, test = dataset.frames("train"), dataset.frames("test")
    assert [f.name.split("/")[-1] for f in train] == [
        f"1700000000.{i}00000000" for i in (0, 1, 2, 3, 5)
    ]
    assert [f.name for f in test] == [f"run/1700000000.{i}00000000" for i in (6, 8, 9)]
    assert dataset.unmatched == 2
    note = capsys.readouterr().err
    assert "2 images on /cam/image with no pose within 0.02 s" in note
    assert "1700000000.400000000, 1700000000.700000000" in note
    for frame in train + test:
        i = round(float(frame.name.split("/")[-1]) * 10) % 100
        np.testing.assert_allclose(frame.pose.position, [i, 2 * i, 0.5])
        np.testing.assert_array_equal(cv2.imread(str(frame.image_path))[:, :, ::-1], images[i])
        assert (frame.camera.fx, frame.camera.fy, frame.camera.cx) == (20.0, 21.0, 7.5)
        assert (frame.camera.width, frame.camera.height) == (16, 12)
        np.testing.assert_allclose(read_frame_depth(frame), 1.0 + i / 10, atol=1e-3)
    # A tighter tolerance matches nothing; the extraction is reused, not redone.
    strict = rosbag_dataset(path, tmp_path, pose_topic="/pose", max_time_difference=0.001)
    assert strict.frames("train") == [] and strict.unmatched == 10


def test_dataset_poses_from_a_tum_file_beside_the_bag(tmp_path):
    path = bag_path(tmp_path, False)
    write_recording(path, False, poses_on=None)
    rows = [f"{1_700_000_000 + i / 10:.6f} {i} 0 0 0 0 0.6 0.8\n" for i in range(10)]
    (tmp_path / "CameraTrajectory.txt").write_text("".join(rows))
    dataset = rosbag_dataset(
        path, tmp_path, trajectory="CameraTrajectory.txt", intrinsics=[30, 30, 8, 6]
    )
    train = dataset.frames("train")
    assert len(train) == 6 and dataset.unmatched == 0
    np.testing.assert_allclose([f.pose.position[0] for f in train], range(6))
    np.testing.assert_allclose(train[0].pose.quaternion, [0.8, 0, 0, 0.6])  # w first
    assert train[0].camera.fx == 30 and train[0].depth_path is None


def test_dataset_poses_from_tf_between_the_named_frames(tmp_path):
    path = bag_path(tmp_path, True)
    bag = BagWriter(path, True)
    for i in range(4):
        bag.image("/cam/image", ns(i / 10), texture(i))
        bag.tf("/tf", ns(i / 10), "map", "base_link", [9, 9, 9])
        bag.tf("/tf", ns(i / 10), "map", "camera", [i, 0, 0])
    bag.close()
    dataset = rosbag_dataset(
        path, tmp_path, pose_topic="/tf", train_time=[[0, 1]], test_time=[[2, 3]]
    )
    np.testing.assert_allclose([f.pose.position[0] for f in dataset.frames("train")], range(4))
    other = rosbag_dataset(path, tmp_path, pose_topic="/tf", tf_child="gripper")
    with pytest.raises(DataError, match="no poses on /tf from map to gripper"):
        other.frames("train")


def test_a_bag_without_poses_is_one_error_naming_the_topic(tmp_path):
    path = bag_path(tmp_path, False)
    write_recording(path, False, poses_on=None)
    with pytest.raises(ConfigError, match="dataset.pose_topic=/pose: no such topic") as refused:
        rosbag_dataset(path, tmp_path, pose_topic="/pose").frames("train")
    assert "\n" not in str(refused.value)
    with pytest.raises(ConfigError, match="give the poses one way"):
        rosbag_dataset(path, tmp_path)


@pytest.mark.parametrize(
    ("options", "key"),
    [
        ({"train_time": [[1, 0]]}, "dataset.train_time"),
        ({"test_time": "soon"}, "dataset.test_time"),
        ({"test_time": [[0.5, 1]]}, "overlap"),
        ({"intrinsics": [1, 2]}, "dataset.intrinsics"),
        ({"bag": None}, "dataset.bag"),
    ],
)
def test_bad_options_are_one_config_error_naming_the_key(tmp_path, options, key):
    with pytest.raises(ConfigError, match=key):
        rosbag_dataset(tmp_path / "x.bag", tmp_path, pose_topic="/pose", **options)


def test_without_test_time_every_posed_image_is_the_map_and_none_is_scored(tmp_path):
    path = bag_path(tmp_path, True)
    write_recording(path, True)
    dataset = rosbag_dataset(path, tmp_path, pose_topic="/pose", train_time=None, test_time=None)
    assert not dataset.has_test_split
    assert len(dataset.frames("train")) == 8 and dataset.frames("test") == []
    assert "dataset.test_time is not set" in dataset.split_source("test")
    # Without train_time the map is every posed image outside the test ranges.
    rest = rosbag_dataset(path, tmp_path, pose_topic="/pose", train_time=None)
    assert rest.has_test_split
    tenths = [round(float(f.name.split("/")[-1]) * 10) % 100 for f in rest.frames("train")]
    assert tenths == [0, 1, 2, 3, 5]
    assert len(rest.frames("test")) == 3


def test_a_connection_with_a_non_standard_type_hash_is_refused(tmp_path):
    """The bag's own message definitions are never compiled: a type recorded with
    another definition than the standard one is refused, not decoded by guess."""
    from rosbags import rosbag1

    path = tmp_path / "odd.bag"
    types = standard_types(True)
    msgdef, _ = types.generate_msgdef(rosbag_source.IMAGE)
    with rosbag1.Writer(path) as writer:
        connection = writer.add_connection(
            "/cam", rosbag_source.IMAGE, msgdef=msgdef, md5sum="0" * 32
        )
        writer.write(connection, ns(0), b"\0" * 64)
    with pytest.raises(DataError, match="not the standard"):
        list(bag_frames(path, "/cam"))


def test_odometry_poses_and_32fc1_depth(tmp_path):
    path = bag_path(tmp_path, False)
    bag = BagWriter(path, False)
    for i in range(3):
        bag.image("/cam/image", ns(i / 10), texture(i))
        bag.depth("/cam/depth", ns(i / 10), np.full((12, 16), 2.5), "32FC1")
        point = bag.Point(x=float(i), y=0.0, z=0.0)
        pose = bag.Pose(position=point, orientation=bag.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
        covariance = bag.PoseWithCovariance(pose=pose, covariance=np.zeros(36))
        twist = bag.TwistWithCovariance(
            twist=bag.Twist(
                linear=bag.Vector3(x=0.0, y=0.0, z=0.0), angular=bag.Vector3(x=0.0, y=0.0, z=0.0)
            ),
            covariance=np.zeros(36),
        )
        odometry = bag.Odometry(
            header=bag.header(ns(i / 10), "odom"),
            child_frame_id="base",
            pose=covariance,
            twist=twist,
        )
        bag.write("/odom", odometry, ns(i / 10))
    bag.close()
    dataset = rosbag_dataset(
        path,
        tmp_path,
        pose_topic="/odom",
        depth_topic="/cam/depth",
        intrinsics=[20, 20, 8, 6],
        train_time=[[0, 1]],
        test_time=[[1, 2]],
    )
    train = dataset.frames("train")
    np.testing.assert_allclose([f.pose.position[0] for f in train], [0, 1, 2])
    np.testing.assert_allclose(read_frame_depth(train[0]), 2.5)


@pytest.mark.slow
def test_a_map_from_a_bag_through_the_command_line(tmp_path):
    """conf/dataset/rosbag.yaml as a user gives it: relocalize builds the map and the
    model file from a bag whose poses are ORB-SLAM2's TUM file beside it (a tiny
    network)."""
    from tests.cli_runs import relocfw_here
    from tests.conftest import TINY_MODEL

    write_recording(tmp_path / "run.bag", True, poses_on=None)
    rows = [f"{1_700_000_000 + i / 10:.6f} {i} {i % 3} 0.5 0 0 0 1\n" for i in range(10)]
    (tmp_path / "CameraTrajectory.txt").write_text("".join(r for i, r in enumerate(rows) if i != 4))
    finished = relocfw_here(
        [
            "dataset=rosbag",
            "dataset.bag=run.bag",
            "dataset.image_topic=/cam/image",
            "dataset.trajectory=CameraTrajectory.txt",
            "dataset.camera_info_topic=/cam/info",
            "dataset.train_time=[[0,0.6]]",
            "dataset.test_time=[[0.6,1]]",
            "hydra.run.dir=out",
            *TINY_MODEL,
            "k=2",
        ],
        tmp_path,
    )
    assert finished.returncode == 0, finished.stderr
    assert (tmp_path / "out" / "model.relocfw").is_file()
    assert "1 image on /cam/image with no pose" in finished.stderr


def test_a_bag_without_time_ranges_is_all_map_and_the_run_scores_nothing(tmp_path):
    """No dataset.train_time nor test_time: every posed image is the map; the run
    writes the model file and says in one line that nothing was scored."""
    from tests.cli_runs import relocfw_here
    from tests.conftest import TINY_MODEL

    write_recording(tmp_path / "run.bag", True)
    finished = relocfw_here(
        [
            "dataset=rosbag",
            "dataset.bag=run.bag",
            "dataset.image_topic=/cam/image",
            "dataset.pose_topic=/pose",
            "hydra.run.dir=out",
            *TINY_MODEL,
            "k=2",
        ],
        tmp_path,
    )
    assert finished.returncode == 0, finished.stderr
    assert (tmp_path / "out" / "model.relocfw").is_file()
    assert not (tmp_path / "out" / "results.csv").exists()
    said = [line for line in finished.stdout.splitlines() if "scored" in line]
    assert said == [
        "nothing was scored: no test frames (dataset.test_time is not set); the map holds 8 images"
    ]


def test_under_skip_an_undecodable_image_is_listed_again_when_the_extraction_is_reused(
    tmp_path,
):
    path = bag_path(tmp_path, False)
    bag = BagWriter(path, False)
    for i in range(3):
        bag.image("/cam/image", ns(i / 10), texture(i))
        bag.pose("/pose", ns(i / 10), [i, 0, 0], [0, 0, 0, 1])
    short = bag.Image(
        header=bag.header(ns(0.3)), height=12, width=16, encoding="rgb8", is_bigendian=0,
        step=48, data=np.zeros(10, np.uint8),
    )  # fmt: skip
    bag.write("/cam/image", short, ns(0.3))
    bag.close()
    for _ in range(2):  # extracted, then reused
        dataset = rosbag_dataset(
            path,
            tmp_path,
            pose_topic="/pose",
            on_error="skip",
            train_time=[[0, 1]],
            test_time=[[1, 2]],
        )
        assert len(dataset.frames("train")) == 3
        (problem,) = dataset.on_error.skipped
        assert str(path) in problem and "too few" in problem
    with pytest.raises(DataError, match="too few"):
        rosbag_dataset(
            path, tmp_path, pose_topic="/pose", train_time=[[0, 1]], test_time=[[1, 2]]
        ).frames("train")
