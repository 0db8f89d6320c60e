"""A CompressedImage that does not decode is one DataError naming its topic and stamp:
read through the same header reader as files and the service, so localize's and the
rosbag dataset's on_error=skip leave it out and on_error=fail stops in one line."""

from __future__ import annotations

import struct
import zlib
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from relocfw import QueryOptions, Relocalizer
from relocfw.core.errors import DataError
from relocfw.data.ros_images import COMPRESSED_IMAGE, colour_image
from tests.core.test_image_headers import jpeg, tem_trap, with_frame_size

pytest.importorskip("rosbags")

TOPIC = "/cam/image/compressed"


def png_announcing(width: int, height: int) -> bytes:
    """A 1 x 1 PNG (91 bytes) whose IHDR, its CRC valid, announces width x height."""
    data = bytearray(cv2.imencode(".png", np.zeros((1, 1, 3), np.uint8))[1].tobytes())
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    return bytes(data)


def compressed(data: bytes, sec: int = 1_700_000_000, nanosec: int = 500_000_000):
    stamp = SimpleNamespace(sec=sec, nanosec=nanosec)
    payload = np.frombuffer(data, np.uint8)
    return SimpleNamespace(header=SimpleNamespace(stamp=stamp), format="png", data=payload)


def test_a_compressed_image_announcing_too_many_pixels_is_one_data_error():
    bomb = png_announcing(40000, 40000)
    assert len(bomb) < 100
    with pytest.raises(DataError) as refused:
        colour_image(compressed(bomb), COMPRESSED_IMAGE, TOPIC)
    assert str(refused.value).startswith(f"{TOPIC} (stamp 1700000000.500000000): ")
    assert "40000 x 40000" in str(refused.value)


def test_a_compressed_image_is_read_through_the_shared_header_reader():
    # The TEM trap shows an 8 x 8 frame header to a reader that gives FF01 a length.
    trapped = with_frame_size(tem_trap(jpeg()), 60000, 60000)
    with pytest.raises(DataError, match=r"announces 60000 x 60000"):
        colour_image(compressed(trapped), COMPRESSED_IMAGE, TOPIC)
    damaged = png_announcing(4, 4)[:20]
    with pytest.raises(DataError, match=rf"^{TOPIC} \(stamp .*damaged PNG header"):
        colour_image(compressed(damaged), COMPRESSED_IMAGE, TOPIC)


@pytest.mark.parametrize("extension", [".tiff", ".bmp", ".webp"])
def test_a_compressed_image_that_is_not_png_or_jpeg_is_refused_naming_it(extension):
    # Formats whose headers are not read are bounded only by OpenCV's 2^30 pixels:
    # refused as the service refuses them, before decoding.
    other = cv2.imencode(extension, np.zeros((4, 6, 3), np.uint8))[1].tobytes()
    assert cv2.imdecode(np.frombuffer(other, np.uint8), cv2.IMREAD_COLOR).shape == (4, 6, 3)
    with pytest.raises(DataError) as refused:
        colour_image(compressed(other), COMPRESSED_IMAGE, TOPIC)
    message = str(refused.value)
    assert message.startswith(f"{TOPIC} (stamp 1700000000.500000000): compressed image (png)")
    assert "not a PNG or JPEG" in message and "\n" not in message


def test_an_opencv_error_while_decoding_names_the_topic(monkeypatch):
    import relocfw.data.ros_images as ros_images

    def failing(*_):
        raise cv2.error("OpenCV(4) error: (-4:Insufficient memory) Failed to allocate 9 bytes")

    monkeypatch.setattr(ros_images.cv2, "imdecode", failing)
    good = cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))[1].tobytes()
    with pytest.raises(DataError, match=rf"^{TOPIC} \(stamp .*Failed to allocate 9 bytes"):
        colour_image(compressed(good), COMPRESSED_IMAGE, TOPIC)


def write_bag_with_a_bomb(path, height: int, width: int) -> list[np.ndarray]:
    """A ROS 2 bag of three CompressedImage frames, the middle one a PNG announcing
    40000 x 40000; poses for every frame on /pose."""
    from tests.data.test_rosbag import BagWriter, ns

    frames = [
        np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)
        for seed in range(3)
    ]
    bag = BagWriter(path, False)
    for i, rgb in enumerate(frames):
        if i == 1:
            message = bag.CompressedImage(
                header=bag.header(ns(0.1)),
                format="png",
                data=np.frombuffer(png_announcing(40000, 40000), np.uint8),
            )
            bag.write(TOPIC, message, ns(0.1))
        else:
            bag.compressed(TOPIC, ns(i / 10), rgb)
        bag.pose("/pose", ns(i / 10), [i, 0, 0], [0, 0, 0, 1])
    bag.close()
    return frames


@pytest.fixture
def model(tmp_path):
    """A tiny saved model (a 32-pixel PoseNet, a three-image map)."""
    import torch

    from relocfw.model.model_file import save_model
    from relocfw.plugins.exhaustive_index import ExhaustiveIndex
    from relocfw.plugins.posenet import PoseNet
    from relocfw.plugins.sweep_crop import SweepCrop

    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.125, feature_dim=32)
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop(), QueryOptions())
    relocalizer.fit([np.full((36, 48, 3), value, np.uint8) for value in (0, 100, 200)])
    parts = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 32}}
    return save_model(tmp_path / "model.relocfw", relocalizer, parts, {})


def test_localize_skips_the_bad_message_under_skip_and_names_it_under_fail(model, tmp_path):
    from tests.app.test_localize_streams import HEIGHT, WIDTH, localize

    bag = tmp_path / "bag"
    write_bag_with_a_bomb(bag, HEIGHT, WIDTH)

    skip_dir = tmp_path / "skip"
    result = localize(model, bag, skip_dir, f"localize.topic={TOPIC}", "localize.on_error=skip")
    assert result.returncode == 0, result.stderr
    answered = [line.split()[0] for line in (skip_dir / "poses.txt").read_text().splitlines()]
    assert answered[1:] == ["1700000000.000000000", "1700000000.200000000"]  # after the header
    (skipped,) = (skip_dir / "skipped.txt").read_text().splitlines()
    assert skipped.startswith(f"{TOPIC} (stamp 1700000000.100000000): ")
    assert "40000 x 40000" in skipped

    fail_dir = tmp_path / "fail"
    result = localize(model, bag, fail_dir, f"localize.topic={TOPIC}")
    assert result.returncode == 2
    *notes, line = result.stderr.splitlines()  # the note says where the answers are
    assert [note.startswith("localize: stopped after 1 frames") for note in notes] == [True]
    assert line.startswith(f"error: {TOPIC} (stamp 1700000000.100000000): ")
    assert "Traceback" not in result.stderr


def test_the_rosbag_dataset_skips_the_bad_message_under_skip(tmp_path):
    from tests.data.test_rosbag import rosbag_dataset

    bag = tmp_path / "run"
    write_bag_with_a_bomb(bag, 12, 16)
    options = dict(image_topic=TOPIC, pose_topic="/pose", train_time=[[0, 1]], test_time=[[1, 2]])
    dataset = rosbag_dataset(bag, tmp_path, on_error="skip", **options)
    assert len(dataset.frames("train")) == 2
    (problem,) = dataset.on_error.skipped
    assert str(bag) in problem and TOPIC in problem and "40000 x 40000" in problem
    with pytest.raises(DataError, match=r"40000 x 40000"):
        rosbag_dataset(bag, tmp_path / "again", **options).frames("train")
