"""task=topics: a bag's topics, types, counts, rates and first / last stamps, for ROS 1
and ROS 2 bags written here with rosbags; bad paths end in one line naming the key."""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.data.bag_topics import topic_stats
from tests.cli_runs import relocfw_here
from tests.data.test_rosbag import BagWriter, bag_path, ns, texture

pytest.importorskip("rosbags")


def write_bag(tmp_path, ros1: bool):
    """Images at 10 Hz for 0.9 s (10), poses at 20 Hz (19), one camera info."""
    path = bag_path(tmp_path, ros1)
    bag = BagWriter(path, ros1)
    bag.camera_info("/cam/info", ns(0.05), [20.0, 0, 7.5, 0, 21.0, 5.5, 0, 0, 1], 16, 12)
    for i in range(10):
        bag.image("/cam/image", ns(i / 10), texture(i))
    for i in range(19):
        bag.pose("/pose", ns(i / 20), [i, 0, 0], [0, 0, 0, 1])
    bag.close()
    return path


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_topic_stats_give_type_count_rate_and_first_and_last_stamp(tmp_path, ros1):
    stats = {s.name: s for s in topic_stats(write_bag(tmp_path, ros1))}
    assert sorted(stats) == ["/cam/image", "/cam/info", "/pose"]
    image, info, pose = stats["/cam/image"], stats["/cam/info"], stats["/pose"]
    assert (image.msgtype, image.count) == ("sensor_msgs/msg/Image", 10)
    assert (pose.msgtype, pose.count) == ("geometry_msgs/msg/PoseStamped", 19)
    assert (image.first_ns, image.last_ns) == (ns(0), ns(0.9))
    assert (pose.first_ns, pose.last_ns) == (ns(0), ns(0.9))
    np.testing.assert_allclose([image.rate_hz, pose.rate_hz], [10.0, 20.0])
    assert info.count == 1 and info.rate_hz is None  # one message has no rate


@pytest.mark.parametrize("key", ["localize.images", "dataset.bag"])
@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_task_topics_prints_one_row_per_topic(tmp_path, ros1, key):
    path = write_bag(tmp_path, ros1)
    dataset = ["dataset=rosbag"] if key == "dataset.bag" else []
    finished = relocfw_here(["task=topics", *dataset, f"{key}={path.name}"], tmp_path)
    assert finished.returncode == 0, finished.stderr
    lines = finished.stdout.splitlines()
    assert f"{path.name}: ROS {1 if ros1 else 2} bag, 3 topics, 30 messages" in lines[0]
    rows = {line.split()[0]: line.split() for line in lines if line.startswith("/")}
    # Seconds from the bag's first message, as dataset.train_time counts them.
    assert "first message at bag time 1700000000.000000000 s" in lines[0]
    assert rows["/cam/image"][1:] == ["sensor_msgs/msg/Image", "10", "10.00", "0.000", "0.900"]
    assert rows["/cam/info"][4:] == ["0.050", "0.050"]
    assert rows["/pose"][1:4] == ["geometry_msgs/msg/PoseStamped", "19", "20.00"]
    assert rows["/cam/info"][1:4] == ["sensor_msgs/msg/CameraInfo", "1", "-"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["localize.images=missing.bag"], "localize.images=missing.bag: bag not found"),
        (["dataset=rosbag", "dataset.bag=missing.bag"], "dataset.bag=missing.bag: bag not found"),
        (["localize.images=notes.txt"], "localize.images=notes.txt: "),
        ([], "task=topics lists a bag's topics: pass localize.images=BAG (or dataset.bag=BAG"),
    ],
)
def test_a_path_that_is_no_bag_is_one_line_naming_the_key(tmp_path, args, message):
    (tmp_path / "notes.txt").write_text("not a bag\n")
    finished = relocfw_here(["task=topics", *args], tmp_path)
    assert finished.returncode == 2
    assert finished.stderr.startswith(f"error: {message}"), finished.stderr
    assert len(finished.stderr.strip().splitlines()) == 1, finished.stderr
