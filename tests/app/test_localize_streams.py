"""task=localize on streams: a video (and a bag) localize frame by frame with their own
timestamps and the poses their frames get as image files; a frame that does not decode
is listed under localize.on_error=skip and stops the run under fail; a killed run
keeps every row it wrote, whole."""

from __future__ import annotations

import csv
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from relocfw import QueryOptions, Relocalizer
from relocfw.app.answer_files import COLUMNS
from relocfw.model.model_file import save_model
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop
from tests.cli_runs import relocfw_here
from tests.data.test_streams import damage_frame, frame_pixels, write_ros2_bag, write_video

HEIGHT, WIDTH = 36, 48
TOPIC = "/camera/color/image_raw"


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """A tiny saved model whose answers differ from frame to frame."""
    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.125, feature_dim=32)
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop(), QueryOptions())
    relocalizer.fit([p[:, :, ::-1].copy() for p in frame_pixels(3, HEIGHT, WIDTH)])
    options = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 32}}
    path = tmp_path_factory.mktemp("model") / "model.relocfw"
    return save_model(path, relocalizer, options, {})


def localize(model: Path, images: Path, run_dir: Path, *extra: str):
    args = [
        "task=localize",
        f"localize.model={model}",
        f"localize.images={images}",
        "engine=torch",
        "quiet=true",
        f"hydra.run.dir={run_dir}",
        *extra,
    ]
    return relocfw_here(args, run_dir.parent)


def read_table(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def pose_rows(path: Path) -> list[list[str]]:
    return [line.split(" ") for line in path.read_text().splitlines()[1:]]


def as_png_files(frames: list[np.ndarray], folder: Path) -> Path:
    """The RGB frames as PNG files (lossless), named so they sort in order."""
    folder.mkdir()
    for i, rgb in enumerate(frames):
        cv2.imwrite(str(folder / f"frame-{i:03d}.png"), rgb[:, :, ::-1])
    return folder


def decoded_rgb(video: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(video))
    frames = []
    while (found := capture.read())[0]:
        frames.append(found[1][:, :, ::-1])
    capture.release()
    return frames


def test_a_video_gives_a_row_per_frame_with_its_times_and_its_frames_poses(model, tmp_path):
    video = write_video(tmp_path / "run.avi", 5, HEIGHT, WIDTH)
    result = localize(model, video, tmp_path / "video")
    assert result.returncode == 0, result.stderr
    # The same frames, as OpenCV decodes them, given as PNG files.
    pngs = as_png_files(decoded_rgb(video), tmp_path / "pngs")
    assert localize(model, pngs, tmp_path / "files").returncode == 0
    streamed, files = (
        pose_rows(tmp_path / "video" / "poses.txt"),
        pose_rows(tmp_path / "files" / "poses.txt"),
    )
    assert [row[0] for row in streamed] == [f"{i / 10:.9f}" for i in range(5)]
    assert [row[1:] for row in streamed] == [row[1:] for row in files]
    assert len({tuple(row[1:]) for row in streamed}) == 5  # the frames' own answers
    table = read_table(tmp_path / "video" / "localization.csv")
    assert list(table[0]) == list(COLUMNS)
    assert [row["image"] for row in table] == [f"{video}#{i}" for i in range(5)]
    assert all(float(row["ms"]) > 0 for row in table)


def test_a_frame_that_does_not_decode_is_listed_under_skip(model, tmp_path):
    video = write_video(tmp_path / "run.avi", 6, HEIGHT, WIDTH)
    damage_frame(video, 2)
    run_dir = tmp_path / "run"
    result = localize(model, video, run_dir, "localize.on_error=skip")
    assert result.returncode == 0, result.stderr
    stamps = [row[0] for row in pose_rows(run_dir / "poses.txt")]
    assert stamps == ["0.000000000", "0.100000000", "0.300000000", "0.400000000", "0.500000000"]
    skipped = (run_dir / "skipped.txt").read_text().splitlines()
    assert len(skipped) == 1 and skipped[0].startswith(f"{video}#2 ")
    assert result.stderr == (
        "localize: 1 frames could not be decoded and were skipped "
        f"(localize.on_error=skip): {run_dir / 'skipped.txt'}\n"
    )


def test_a_frame_that_does_not_decode_stops_the_run_under_fail(model, tmp_path):
    video = write_video(tmp_path / "run.avi", 6, HEIGHT, WIDTH)
    damage_frame(video, 2)
    run_dir = tmp_path / "run"
    result = localize(model, video, run_dir)
    assert result.returncode == 2
    assert f"error: {video}#2 (at about 0.200000000 s): it does not decode" in result.stderr
    assert [row[0] for row in pose_rows(run_dir / "poses.txt.partial")] == [
        "0.000000000",
        "0.100000000",
    ]
    assert not (run_dir / "poses.txt").exists()


def test_an_unknown_on_error_is_refused_before_any_work(model, tmp_path):
    result = localize(model, tmp_path, tmp_path / "run", "localize.on_error=ignore")
    assert result.returncode == 2
    assert result.stderr == (
        "error: localize.on_error=ignore: Invalid value 'ignore', expected one of [fail, skip]\n"
    )


def test_a_bag_topic_localizes_as_its_frames_do_as_files(model, tmp_path):
    pytest.importorskip("rosbags")
    pytest.importorskip("relocfw.data.rosbag_source")
    frames = [p[:, :, ::-1].copy() for p in frame_pixels(4, HEIGHT, WIDTH)]
    bag = tmp_path / "bag"
    write_ros2_bag(bag, TOPIC, frames, 1_700_000_000 * 10**9)
    result = localize(model, bag, tmp_path / "streamed", f"localize.topic={TOPIC}")
    assert result.returncode == 0, result.stderr
    pngs = as_png_files(frames, tmp_path / "pngs")
    assert localize(model, pngs, tmp_path / "files").returncode == 0
    streamed = pose_rows(tmp_path / "streamed" / "poses.txt")
    files = pose_rows(tmp_path / "files" / "poses.txt")
    assert [row[0] for row in streamed] == [f"1700000000.{i}00000000" for i in range(4)]
    assert [row[1:] for row in streamed] == [row[1:] for row in files]


KILLED = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    import numpy as np
    from relocfw import QueryOptions
    from relocfw.app.tasks.localize import localize_images
    from relocfw.core.values import Crop, Localization, Pose

    class Slow:
        options = QueryOptions(queries_at_once=2)

        def localize(self, image):
            time.sleep(0.02)
            level = float(image[0, 0, 0])
            pose = Pose(np.array([level, 1.0, 2.0]), np.array([1.0, 0, 0, 0]))
            return Localization(pose, Crop(0, 0, 4), 0.25, 1, 0.0)

        def localize_many(self, images, at_once):
            return [self.localize(image) for image in images]

    images = sorted(Path(sys.argv[1]).glob("*.png"))
    localize_images(Slow(), images, Path(sys.argv[2]), quiet=True)
    """
)
POSE_LINE = re.compile(r"\d+( -?\d+\.\d{9}){7}")


def test_killed_localize_keeps_every_row_written_whole(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    count = 1500  # about 30 s of stand-in work: the kill lands long before the end
    for i in range(count):
        cv2.imwrite(str(folder / f"frame-{i:04d}.png"), np.full((2, 2, 3), i % 256, np.uint8))
    run_dir = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen(
        [sys.executable, "-c", KILLED, str(folder), str(run_dir)],
        env=env,
        cwd=Path(__file__).parents[2],
        stderr=subprocess.PIPE,
    )
    partial = run_dir / "poses.txt.partial"
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline and process.poll() is None:
            if partial.exists() and partial.read_bytes().count(b"\n") > 50:
                break
            time.sleep(0.01)
        assert process.poll() is None, process.stderr.read().decode()
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == -signal.SIGKILL
    assert not (run_dir / "poses.txt").exists()
    poses = partial.read_text()
    assert poses.endswith("\n")  # whole lines only
    rows = poses.splitlines()[1:]
    assert 50 <= len(rows) < count
    for position, line in enumerate(rows):
        assert POSE_LINE.fullmatch(line), line
        stamp, x = line.split(" ")[:2]
        assert int(stamp) == position and float(x) == position % 256
    assert (run_dir / "localization.csv.partial").read_bytes().endswith(b"\r\n")
    answers = read_table(run_dir / "localization.csv.partial")
    # Each group reaches poses.txt, then the table: a kill between them leaves the
    # table one group (two frames) behind, never a part of a row.
    assert len(rows) - len(answers) in (0, 2)
    assert all(None not in row and len(row) == len(COLUMNS) for row in answers)
    names = [Path(row["image"]).name for row in answers]
    assert names == [f"frame-{i:04d}.png" for i in range(len(answers))]
