"""A bag's extraction clears what a killed extraction left (`.extracting-*` folders
whose writer is gone), never a live one's; and frames of a bag that share a stamp
get names of their own (the first keeps the stamp, as every unique stamp does)."""

from __future__ import annotations

import os
import time

import pytest

from relocfw.core.atomic_files import release_folder, staging_folder
from relocfw.data.on_error import OnError
from relocfw.data.rosbag_cache import BagTopics, extracted_bag
from relocfw.data.rosbag_source import bag_frames
from tests.data.test_rosbag import BagWriter, bag_path, ns, texture

pytest.importorskip("rosbags")
pytestmark = pytest.mark.skipif(os.name != "posix", reason="flock is POSIX")


def make_old(path, seconds: float = 2 * 86400) -> None:
    past = time.time() - seconds
    os.utime(path, (past, past))


def test_a_killed_extractions_folder_is_cleared_and_a_live_one_kept(tmp_path):
    path = bag_path(tmp_path, ros1=True)
    bag = BagWriter(path, ros1=True)
    for i in range(3):
        bag.image("/cam/image", ns(i / 10), texture(i))
    bag.close()
    bags = tmp_path / "cache" / "bags"
    bags.mkdir(parents=True)
    # A killed extraction: a day-old folder with a frame in it and no writer.
    killed = bags / ".extracting-killed"
    (killed / "rgb").mkdir(parents=True)
    (killed / "rgb" / "1.png").write_bytes(b"x" * 1000)
    make_old(killed)
    # A live one (another run extracting now): as old, but its writer holds its lock.
    live, handle = staging_folder(bags, ".extracting-")
    make_old(live)
    try:
        folder = extracted_bag(path, BagTopics("/cam/image"), tmp_path / "cache", OnError("fail"))
        assert (folder / "bag.json").is_file()
        assert not killed.exists()
        assert live.exists()
    finally:
        release_folder(handle)
    assert sorted(p.name for p in bags.iterdir()) == sorted([folder.name, live.name])


def test_frames_sharing_a_stamp_get_names_of_their_own(tmp_path):
    path = bag_path(tmp_path, ros1=False)
    bag = BagWriter(path, ros1=False)
    stamps = [ns(0.0), ns(0.1), ns(0.1), ns(0.1), ns(0.2)]
    for i, stamp in enumerate(stamps):
        bag.image("/cam/image", stamp, texture(i), bag_time=ns(i / 10))
    bag.close()
    frames = list(bag_frames(path, "/cam/image"))
    assert [f.timestamp for f in frames] == [
        "1700000000.000000000",
        "1700000000.100000000",
        "1700000000.100000000",
        "1700000000.100000000",
        "1700000000.200000000",
    ]
    names = [f.name for f in frames]
    assert len(set(names)) == len(names), names
    # Unique stamps keep their names; a repeat gets its count.
    assert names[:2] == ["1700000000.000000000", "1700000000.100000000"]
    assert names[4] == "1700000000.200000000"
