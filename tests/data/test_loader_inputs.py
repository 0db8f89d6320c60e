"""Loader inputs that used to escape as raw exceptions or silent mix-ups: each is one
DataError naming the file, and dataset.on_error=skip still leaves the entry out."""

import struct
import zlib

import cv2
import numpy as np
import pytest

from relocfw.app.splits import load_split
from relocfw.core import imaging
from relocfw.core.errors import DataError
from relocfw.core.imaging import read_rgb
from relocfw.core.values import Pose
from relocfw.data.cambridge import load_cambridge
from relocfw.data.folder import PoseFolder, load_pose_table
from relocfw.data.frames import Frame, read_good_images
from relocfw.data.on_error import OnError
from relocfw.data.sevenscenes import load_sevenscenes

HEADER = "image,x,y,z,qw,qx,qy,qz\n"
POSE = "1.0,2.0,0.5,1,0,0,0"


def png_announcing(path, width, height):
    """A real small PNG whose IHDR (with a valid CRC) announces width x height."""
    data = bytearray(cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))[1].tobytes())
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    path.write_bytes(bytes(data))
    return path


def test_a_header_announcing_a_huge_image_is_refused_before_decoding(tmp_path):
    huge = png_announcing(tmp_path / "huge.png", 70000, 70000)
    with pytest.raises(DataError, match=r"huge\.png.*70000 x 70000"):
        read_rgb(huge)
    # on_error=skip leaves it out and keeps the good frame.
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), np.zeros((4, 6, 3), np.uint8))
    frames = [
        Frame("huge", huge, Pose([0.0, 0, 0], [1, 0, 0, 0])),
        Frame("good", good, Pose([0.0, 0, 0], [1, 0, 0, 0])),
    ]
    skip = OnError("skip")
    kept, images = read_good_images(frames, skip, quiet=True)
    assert [f.name for f in kept] == ["good"] and len(images) == 1
    assert "huge.png" in skip.skipped[0]


def test_a_jpeg_header_is_read_too_and_the_cap_lets_normal_images_through(tmp_path):
    big = tmp_path / "big.jpg"
    cv2.imwrite(str(big), np.zeros((8, 8, 3), np.uint8))
    data = bytearray(big.read_bytes())
    frame = next(i for i in range(2, len(data) - 9) if data[i] == 0xFF and data[i + 1] == 0xC0)
    data[frame + 5 : frame + 9] = struct.pack(">HH", 60000, 60000)
    big.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"big\.jpg.*60000 x 60000"):
        read_rgb(big)
    assert imaging.MAX_IMAGE_PIXELS >= 8192 * 8192
    small = tmp_path / "small.jpg"
    cv2.imwrite(str(small), np.zeros((5, 7, 3), np.uint8))
    assert read_rgb(small).shape == (5, 7, 3)


def test_a_byte_that_is_not_utf8_in_a_split_file_names_the_file(tmp_path):
    (tmp_path / "TestSplit.txt").write_bytes(b"sequence1\nsequence\xff2\n")
    with pytest.raises(DataError, match=r"TestSplit\.txt.*0xff.*not UTF-8"):
        load_sevenscenes(tmp_path, None, "test")


def test_a_csv_image_path_with_a_space_is_read_whole(tmp_path):
    (tmp_path / "poses.csv").write_text(
        HEADER + f"images/frame one.png,{POSE}\n" + f'"images/frame, two.png",{POSE}\n'
    )
    frames = load_pose_table(tmp_path / "poses.csv", tmp_path)
    assert [f.image_path for f in frames] == [
        tmp_path / "images/frame one.png",
        tmp_path / "images/frame, two.png",
    ]


def test_a_space_in_a_whitespace_separated_path_is_named(tmp_path):
    (tmp_path / "poses.txt").write_text(
        "image x y z qw qx qy qz\nimages/frame one.png 1 2 0.5 1 0 0 0\n"
    )
    with pytest.raises(DataError, match=r"poses\.txt:2: 9 values.*image path with a space"):
        load_pose_table(tmp_path / "poses.txt", tmp_path)


def test_two_images_with_one_frame_name_are_refused_naming_both(tmp_path):
    (tmp_path / "poses.csv").write_text(HEADER + f"a.png,{POSE}\na.jpg,{POSE}\nb.png,{POSE}\n")
    with pytest.raises(
        DataError, match=r"poses\.csv:3: .*a\.jpg and .*a\.png would both be frame 'a'"
    ):
        load_pose_table(tmp_path / "poses.csv", tmp_path)
    skip = OnError("skip")
    frames = load_pose_table(tmp_path / "poses.csv", tmp_path, skip)
    assert [f.image_path.name for f in frames] == ["a.png", "b.png"]
    assert len(skip.skipped) == 1 and "a.jpg" in skip.skipped[0]


def test_two_cambridge_images_with_one_frame_name_are_refused_naming_both(tmp_path):
    lines = ["Visual Landmark Dataset V1", "ImageFile, Camera Position [X Y Z W P Q R]", ""]
    lines += ["seq1/frame00001.png 1 2 3 1 0 0 0", "seq1/frame00001.jpg 1 2 3 1 0 0 0"]
    (tmp_path / "dataset_test.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"frame00001\.jpg and .*frame00001\.png would both"):
        load_cambridge(tmp_path, "test")


def test_a_16_bit_tiff_depth_map_is_not_read_as_colour(tmp_path):
    depth = tmp_path / "frame.depth.tiff"
    cv2.imwrite(str(depth), np.full((4, 6), 1234, np.uint16))
    with pytest.raises(DataError, match=r"frame\.depth\.tiff is a 16-bit .*TIFF"):
        read_rgb(depth)
    colour = tmp_path / "frame.tiff"
    cv2.imwrite(str(colour), np.full((4, 6, 3), 7, np.uint8))
    assert read_rgb(colour).shape == (4, 6, 3)  # an 8-bit colour TIFF still reads


def test_an_empty_split_names_its_file(tmp_path):
    (tmp_path / "train.csv").write_text(HEADER + f"a.png,{POSE}\n")
    (tmp_path / "test.csv").write_text(HEADER)
    with pytest.raises(DataError, match=r"test\.csv: the test split is empty"):
        load_split(PoseFolder(str(tmp_path)), "test", quiet=True)
