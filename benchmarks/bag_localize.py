"""A robot's recording as a ROS 2 bag: the same poses as the image files it was made of.

Writes the test frames of a 7-Scenes scene (in order, one sequence after another) into
a ROS 2 bag (sqlite3) as sensor_msgs/Image rgb8 on --topic, stamped 1/30 s apart, with
rosbags itself. Then runs `relocfw task=localize` with one model file twice: on the
bag (`localize.images=BAG localize.topic=TOPIC`) and on the image files (a folder of
links named by frame number), and compares the two poses.txt files row by row.
Writes JSON atomically and prints one line.

    .venv/bin/python benchmarks/bag_localize.py --model outputs/DATE/TIME/model.relocfw \
        --scene ../shared/data/7scenes-redkitchen/redkitchen --sequences 2 4 6 \
        --out benchmarks/results/bag_localize.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from relocfw.core.atomic_files import write_text_atomic
from relocfw.core.imaging import read_rgb

FRAME_SECONDS = 1 / 30


def test_frames(scene: Path, sequences: list[int]) -> list[Path]:
    """The colour frames of the given sequences, in recording order."""
    frames: list[Path] = []
    for number in sequences:
        folder = scene / f"seq-{number:02d}"
        frames += sorted(folder.glob("frame-*.color.*"))
    if not frames:
        raise SystemExit(f"no colour frames in {scene} sequences {sequences}")
    return frames


def write_bag(frames: list[Path], bag: Path, topic: str) -> None:
    """Each frame as a sensor_msgs/Image (rgb8) on `topic`, FRAME_SECONDS apart."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE)
    image_type = types.types["sensor_msgs/msg/Image"]
    header_type = types.types["std_msgs/msg/Header"]
    time_type = types.types["builtin_interfaces/msg/Time"]
    with Writer(bag, version=9) as writer:
        connection = writer.add_connection(topic, image_type.__msgtype__, typestore=types)
        for index, frame in enumerate(frames):
            rgb = read_rgb(frame)
            stamp = round((1.0 + index * FRAME_SECONDS) * 1e9)
            header = header_type(
                stamp=time_type(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="camera"
            )
            message = image_type(
                header=header,
                height=rgb.shape[0],
                width=rgb.shape[1],
                encoding="rgb8",
                is_bigendian=0,
                step=rgb.shape[1] * 3,
                data=np.ascontiguousarray(rgb).reshape(-1),
            )
            data = types.serialize_cdr(message, image_type.__msgtype__)
            writer.write(connection, stamp, bytes(data))


def localize(model: Path, images: str, run_dir: Path, topic: str | None) -> float:
    """Run task=localize into `run_dir`; its wall time in seconds."""
    command = [
        str(Path(sys.executable).with_name("relocfw")),
        "task=localize",
        f"localize.model={model}",
        f"localize.images={images}",
        f"hydra.run.dir={run_dir}",
    ]
    if topic is not None:
        command.append(f"localize.topic={topic}")
    started = time.perf_counter()
    subprocess.run(command, check=True)
    return time.perf_counter() - started


def positions(run_dir: Path) -> np.ndarray:
    """poses.txt's positions, [N, 3], in row order."""
    rows = [line.split() for line in (run_dir / "poses.txt").read_text().splitlines()]
    return np.array([[float(v) for v in row[1:4]] for row in rows if not row[0].startswith("#")])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--sequences", type=int, nargs="+", default=[2, 4, 6])
    parser.add_argument("--topic", default="/camera/color/image_raw")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/bag_localize.json"))
    args = parser.parse_args()
    frames = test_frames(args.scene, args.sequences)
    with tempfile.TemporaryDirectory() as work:
        work_dir = Path(work)
        bag = work_dir / "recording"
        write_bag(frames, bag, args.topic)
        files = work_dir / "files"
        files.mkdir()
        for index, frame in enumerate(frames):
            (files / f"{index:06d}{frame.suffix}").symlink_to(frame.resolve())
        bag_seconds = localize(args.model, str(bag), work_dir / "from_bag", args.topic)
        file_seconds = localize(args.model, str(files), work_dir / "from_files", None)
        from_bag, from_files = positions(work_dir / "from_bag"), positions(work_dir / "from_files")
    if from_bag.shape != from_files.shape:
        raise SystemExit(f"{len(from_bag)} poses from the bag, {len(from_files)} from the files")
    largest = float(np.abs(from_bag - from_files).max())
    result = {
        "scene": str(args.scene),
        "sequences": args.sequences,
        "frames": len(frames),
        "model": str(args.model),
        "largest_position_difference_m": largest,
        "bag_run_seconds": round(bag_seconds, 1),
        "files_run_seconds": round(file_seconds, 1),
    }
    write_text_atomic(json.dumps(result, indent=2) + "\n", args.out)
    print(
        f"{len(frames)} frames: largest position difference bag vs files {largest:.3g} m "
        f"(bag run {bag_seconds:.0f} s, files run {file_seconds:.0f} s) -> {args.out}"
    )


if __name__ == "__main__":
    main()
