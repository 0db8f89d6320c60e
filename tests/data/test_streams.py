"""Frame sources for task=localize: image files (today's order and timestamps), a video
(OpenCV, its own timestamps, a damaged frame as an error frame) and the dispatch to a
ROS bag."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.data.streams import count_frames, open_frames, source_kind

FPS = 10.0


def frame_pixels(count: int, height: int = 24, width: int = 32) -> list[np.ndarray]:
    """`count` BGR frames, each a different pattern (smooth, so MJPG keeps them close)."""
    rows, cols = np.mgrid[0:height, 0:width]
    return [
        np.stack(
            [
                (rows * 8 + 20 * i) % 256,
                (cols * 6 + 30 * i) % 256,
                np.full_like(rows, 40 * i % 256),
            ],
            axis=2,
        ).astype(np.uint8)
        for i in range(count)
    ]


def write_video(path: Path, count: int, height: int = 24, width: int = 32) -> Path:
    """An MJPG .avi of `count` frames at FPS (MJPG needs no codec beyond OpenCV's)."""
    frames = frame_pixels(count, height, width)
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (width, height))
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path


def damage_frame(path: Path, index: int) -> None:
    """Zero the JPEG data of frame `index` of an MJPG .avi: FFmpeg finds no image in it."""
    data = bytearray(path.read_bytes())
    starts = [i for i in range(len(data) - 2) if data[i : i + 3] == b"\xff\xd8\xff"]
    start = starts[index]
    end = starts[index + 1] if index + 1 < len(starts) else data.index(b"idx1")
    data[start : end - 8] = bytes(end - 8 - start)  # the next chunk's header stays
    path.write_bytes(bytes(data))


def decoded_rgb(path: Path) -> list[np.ndarray]:
    """The frames OpenCV decodes from `path`, as RGB."""
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, bgr = capture.read()
        if not ok:
            break
        frames.append(bgr[:, :, ::-1])
    capture.release()
    return frames


def test_image_files_keep_todays_order_names_and_timestamps(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    for name in ("b.png", "1305031102.175304.png", "a.png"):
        cv2.imwrite(str(folder / name), np.full((4, 6, 3), 9, np.uint8))
    (folder / "notes.txt").write_text("not an image")
    frames = list(open_frames(str(folder)))
    names = [Path(f.name).name for f in frames]
    assert names == ["1305031102.175304.png", "a.png", "b.png"]
    assert [f.timestamp for f in frames] == ["1305031102.175304", "1", "2"]
    assert all(f.image.shape == (4, 6, 3) and f.error is None for f in frames)
    assert count_frames(str(folder)) == 3
    assert count_frames(str(folder / "*.png")) == 3


def test_an_image_that_does_not_decode_is_an_error_frame_naming_it(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    cv2.imwrite(str(folder / "0.png"), np.zeros((4, 6, 3), np.uint8))
    (folder / "1.png").write_bytes(b"not a png")
    good, bad = open_frames(str(folder))
    assert good.error is None and bad.image is None
    assert "1.png" in bad.error and bad.timestamp == "1"


def test_a_video_gives_every_frame_with_its_own_timestamp(tmp_path):
    video = write_video(tmp_path / "run.avi", 5)
    assert source_kind(str(video)) == "video"
    frames = list(open_frames(str(video)))
    assert [f.name for f in frames] == [f"{video}#{i}" for i in range(5)]
    assert [f.timestamp for f in frames] == [f"{i / FPS:.9f}" for i in range(5)]
    for frame, expected in zip(frames, decoded_rgb(video), strict=True):
        assert frame.error is None and frame.image.dtype == np.uint8
        assert np.array_equal(frame.image, expected)  # RGB, as OpenCV decodes it
    assert count_frames(str(video)) == 5


def test_a_damaged_video_frame_is_an_error_frame_and_the_rest_are_read(tmp_path):
    video = write_video(tmp_path / "run.avi", 6)
    damage_frame(video, 2)
    frames = list(open_frames(str(video)))
    assert len(frames) == 6
    assert [f.error is None for f in frames] == [True, True, False, True, True, True]
    assert frames[2].image is None and f"{video}#2" in frames[2].error
    assert frames[2].timestamp == "0.200000000"  # estimated from the frame rate
    assert [f.timestamp for f in frames[3:]] == ["0.300000000", "0.400000000", "0.500000000"]


def test_a_damaged_stretch_longer_than_the_end_rule_is_read_through(tmp_path):
    # 20 damaged frames in a row: more than END_AFTER_FAILURES, but the header counts
    # the frames after them, so they are read.
    video = write_video(tmp_path / "run.avi", 30)
    for _ in range(20):  # each damage removes a marker: the next frame is the 5th then
        damage_frame(video, 5)
    frames = list(open_frames(str(video)))
    assert [f.error is None for f in frames] == [True] * 5 + [False] * 20 + [True] * 5
    assert [f.timestamp for f in frames[25:]] == [f"{i / FPS:.9f}" for i in range(25, 30)]


def test_a_damaged_last_frame_the_header_counts_is_an_error_frame(tmp_path):
    video = write_video(tmp_path / "run.avi", 4)
    damage_frame(video, 3)
    frames = list(open_frames(str(video)))
    # The header counts 4 frames: the 4th is an error frame, the failed grabs after it
    # (the end of the video) are no frames at all.
    assert [f.error is None for f in frames] == [True, True, True, False]
    assert "does not decode (of 4 frames)" in frames[3].error


def test_a_file_named_as_a_video_that_is_none_is_one_data_error(tmp_path):
    video = tmp_path / "run.mp4"
    video.write_bytes(b"not a video at all")
    with pytest.raises(DataError, match=r"cannot open video .*run\.mp4"):
        open_frames(str(video))


def test_a_topic_for_images_or_a_video_is_refused(tmp_path):
    video = write_video(tmp_path / "run.avi", 2)
    with pytest.raises(ConfigError, match=r"^localize\.topic=/camera is for ROS bags"):
        open_frames(str(video), "/camera")


def test_nothing_named_is_a_config_error_naming_the_key():
    with pytest.raises(ConfigError, match=r"^localize\.images is not set"):
        open_frames("")


@pytest.mark.parametrize("name", ["run.bag", "run.db3", "run.mcap", "folder"])
def test_bags_are_recognised(tmp_path, name):
    path = tmp_path / name
    if name == "folder":
        path.mkdir()
        (path / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    else:
        path.write_bytes(b"")
    assert source_kind(str(path)) == "bag"


def write_ros2_bag(path: Path, topic: str, images: list[np.ndarray], start_ns: int) -> None:
    """A ROS 2 bag of rgb8 sensor_msgs/Image messages, 0.1 s apart (rosbags' writer)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE)
    image_type, header_type, time_type = (
        types.types[name]
        for name in ("sensor_msgs/msg/Image", "std_msgs/msg/Header", "builtin_interfaces/msg/Time")
    )
    with Writer(path, version=9) as writer:
        connection = writer.add_connection(topic, "sensor_msgs/msg/Image", typestore=types)
        for i, rgb in enumerate(images):
            stamp = start_ns + i * 100_000_000
            header = header_type(
                stamp=time_type(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="camera"
            )
            height, width = rgb.shape[:2]
            message = image_type(
                header=header,
                height=height,
                width=width,
                encoding="rgb8",
                is_bigendian=0,
                step=width * 3,
                data=rgb.reshape(-1),
            )
            raw = types.serialize_cdr(message, "sensor_msgs/msg/Image")
            writer.write(connection, stamp, bytes(raw))


def test_a_bag_goes_through_the_bag_reader_with_its_topic(tmp_path):
    pytest.importorskip("rosbags")
    pytest.importorskip("relocfw.data.rosbag_source")
    images = [p[:, :, ::-1].copy() for p in frame_pixels(3)]
    bag = tmp_path / "run"
    write_ros2_bag(bag, "/camera/image_raw", images, 1_700_000_000 * 10**9)
    assert source_kind(str(bag)) == "bag"
    frames = list(open_frames(str(bag), "/camera/image_raw"))
    assert [f.timestamp for f in frames] == [f"1700000000.{i}00000000" for i in range(3)]
    assert all(np.array_equal(f.image, rgb) for f, rgb in zip(frames, images, strict=True))
    assert count_frames(str(bag), "/camera/image_raw") == 3
    with pytest.raises(ConfigError, match=r"^localize\.topic is not set.*/camera/image_raw"):
        open_frames(str(bag))


def test_a_bag_without_rosbags_installed_says_how_to_install_it(tmp_path, monkeypatch):
    pytest.importorskip("relocfw.data.rosbag_source")
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")
    for name in [m for m in sys.modules if m == "rosbags" or m.startswith("rosbags.")]:
        monkeypatch.setitem(sys.modules, name, None)  # as if it were not installed
    monkeypatch.setitem(sys.modules, "rosbags", None)
    with pytest.raises(ConfigError, match=r"pip install relocfw\[robot\]"):
        list(open_frames(str(bag), "/camera/image_raw"))
    with pytest.raises(ConfigError, match=r"pip install relocfw\[robot\]"):
        count_frames(str(bag), "/camera/image_raw")
