"""Pose files in the format of Brachmann et al.'s pseudo ground truths.

Brachmann, Humenberger, Rother and Sattler, "On the Limits of Pseudo Ground Truth in
Visual Camera Re-localisation" (ICCV 2021), published 7-Scenes' (and 12-Scenes') poses
twice: from structure-from-motion (COLMAP, "SfM") and the datasets' own depth SLAM
poses re-expressed for the colour camera ("DSLAM"). Both use one line per image:

    rgb_file qw qx qy qz tx ty tz f

with (q, t) world-to-camera as COLMAP writes it (x_camera = R(q) x_world + t), the
COLOUR camera's pose, and f that camera's focal length in pixels (principal point at
the image centre). `rgb_file` is matched to a frame by its sequence and frame number
(`seq-01/frame-000123.color.png` is sequence 1, frame 123), whatever its extension, so
a copy that re-encoded the images still finds its lines. relocfw reads such files
for datasets in the 7-Scenes layout (relocfw.data.sevenscenes); it has no 12-Scenes
loader.

The file is data: every line is checked (nine fields, finite numbers, a unit
quaternion, a positive focal length, one line per frame) and its size is bounded
before it is read.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from relocfw.core.errors import DataError
from relocfw.core.values import Pose
from relocfw.data.colmap import colmap_to_pose
from relocfw.data.text import data_lines, numbers

# 7-Scenes' largest scene has 26 000 frames (about 3 MB of lines); a pose file many times
# that is not one, and is refused before it is read into memory.
MAX_FILE_BYTES = 64 * 2**20
# The name's last two parts: `seq-01/frame-000123.color.png` (any folder before them).
FRAME_NAME = re.compile(r"(?:^|[/\\])seq-?(\d+)[/\\]frame-(\d+)[^/\\]*$", re.IGNORECASE)
FIELDS = 9  # rgb_file, qw qx qy qz, tx ty tz, f


@dataclass(frozen=True)
class ReferencePose:
    """One line of a pseudo-ground-truth file.

    Attributes:
        pose: the colour camera's camera-to-world pose (relocfw's convention).
        focal: the colour camera's focal length in pixels.
        source: "file:line", for messages.
    """

    pose: Pose
    focal: float
    source: str


@dataclass(frozen=True)
class PseudoGroundTruth:
    """A pseudo-ground-truth file's lines by (sequence, frame number)."""

    path: Path
    lines: Mapping[tuple[int, int], ReferencePose]

    def get(self, sequence: int, frame: int) -> ReferencePose | None:
        """The line of sequence `sequence`'s frame `frame`, or None where there is none."""
        return self.lines.get((sequence, frame))

    def has_sequence(self, sequence: int) -> bool:
        """Whether any line is a frame of sequence `sequence`."""
        return any(key[0] == sequence for key in self.lines)


def frame_key(name: str) -> tuple[int, int] | None:
    """(sequence, frame number) of a name such as `seq-01/frame-000123.color.png`,
    or None where it names no sequence and frame."""
    match = FRAME_NAME.search(name)
    return (int(match.group(1)), int(match.group(2))) if match else None


def read_pseudo_ground_truth(path: str | Path) -> PseudoGroundTruth:
    """A pseudo-ground-truth file, every line checked.

    Raises:
        DataError: naming the file for a missing or oversized file, and the file and
            line for a line with the wrong number of fields, a value that is not a
            finite number, a quaternion whose norm is not 1, a focal length that is
            not positive, a name without a sequence and frame number, or a frame
            listed twice.
    """
    path = Path(path)
    if path.is_file() and path.stat().st_size > MAX_FILE_BYTES:
        raise DataError(
            f"{path}: {path.stat().st_size} bytes, more than a pose file of "
            f"{MAX_FILE_BYTES // 2**20} MiB: not a pseudo-ground-truth file"
        )
    poses: dict[tuple[int, int], ReferencePose] = {}
    for source, fields in data_lines(path):
        if len(fields) != FIELDS:
            raise DataError(
                f"{source}: expected 9 fields (rgb_file qw qx qy qz tx ty tz f), "
                f"found {len(fields)}"
            )
        key = frame_key(fields[0])
        if key is None:
            raise DataError(
                f"{source}: {fields[0]!r} names no sequence and frame "
                "(expected a name like seq-01/frame-000000.color.png)"
            )
        values = numbers(fields[1:], source, FIELDS - 1)
        focal = values[7]
        if not math.isfinite(focal) or focal <= 0:
            raise DataError(f"{source}: focal length f must be a positive number, got {focal}")
        pose = colmap_to_pose(values[:4], values[4:7], source)
        if key in poses:
            raise DataError(
                f"{source}: {fields[0]!r} is sequence {key[0]} frame {key[1]} again "
                f"(first at {poses[key].source})"
            )
        poses[key] = ReferencePose(pose, focal, source)
    if not poses:
        raise DataError(f"{path}: holds no pose lines")
    return PseudoGroundTruth(path, poses)
