"""The files task=localize writes as it goes: poses.txt (TUM format), localization.csv
and skipped.txt, each under a `.partial` name until the run finishes."""

from __future__ import annotations

import csv
import io
import os
import sys
from pathlib import Path
from typing import BinaryIO

from relocfw.core.values import Localization
from relocfw.data.stream_frame import StreamFrame
from relocfw.report.evaluation import ANSWER_COLUMNS, POSE_COLUMNS, answer_cells

# ms: the frame's own time, decoding and localizing, in milliseconds (`seconds` is the
# localizing alone, a group's time shared among its frames).
COLUMNS = ("image", "timestamp", *POSE_COLUMNS, *ANSWER_COLUMNS, "ms")
PARTIAL_SUFFIX = ".partial"


class AnswerFiles:
    """poses.txt (TUM format), localization.csv and skipped.txt, written as the answers
    are made.

    The rows go to `poses.txt.partial` and `localization.csv.partial` first: a run
    that stops at frame 900 (a crash, a kill, a bad frame) keeps the 899 rows before
    it there, and a finished run renames them over the final names, so files a
    previous run left under those names are never replaced by a half-written one.
    The rows of a group reach each file in one unbuffered write() of whole lines
    (`flush`), so a killed run leaves whole rows only.
    """

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = Path(run_dir)
        self.poses_path = self.run_dir / "poses.txt"
        self.table_path = self.run_dir / "localization.csv"
        self.skipped_path = self.run_dir / "skipped.txt"
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.poses = partial_of(self.poses_path).open("wb", buffering=0)
        self.table = partial_of(self.table_path).open("wb", buffering=0)
        self.skips: BinaryIO | None = None  # opened at the first skipped frame
        self.pose_lines: list[str] = []
        self.rows = io.StringIO()
        self.writer = csv.writer(self.rows)  # "\r\n" line ends, as csv files have
        self.written = 0
        self.skipped = 0
        self.pose_lines.append("# timestamp tx ty tz qx qy qz qw (camera-to-world)\n")
        self.writer.writerow(COLUMNS)
        self.flush()

    def write(self, frame: StreamFrame, answer: Localization, ms: float) -> None:
        """One frame's answer: a line of poses.txt and a row of localization.csv, on
        disk at the next `flush`."""
        (x, y, z), (qw, qx, qy, qz) = answer.pose.position, answer.pose.quaternion
        values = " ".join(f"{v:.9f}" for v in (x, y, z, qx, qy, qz, qw))
        self.pose_lines.append(f"{frame.timestamp} {values}\n")
        self.writer.writerow(
            [frame.name, frame.timestamp]
            + [f"{v:.9f}" for v in (x, y, z, qw, qx, qy, qz)]
            + answer_cells(answer)
            + [f"{ms:.3f}"]
        )
        self.written += 1

    def skip(self, frame: StreamFrame) -> None:
        """List a frame that could not be decoded in skipped.txt, at once."""
        if self.skips is None:
            self.skips = partial_of(self.skipped_path).open("wb", buffering=0)
        why = (frame.error or "no image").replace("\n", " ")
        write_all(self.skips, f"{why}\n".encode())
        self.skipped += 1

    def flush(self) -> None:
        """Hand what is written to the system, one write() per file: a crash or kill
        of this process after this loses none of it (no fsync per group: that would
        cost a disk round trip per frame, and only a power cut needs it)."""
        write_all(self.poses, "".join(self.pose_lines).encode())
        write_all(self.table, self.rows.getvalue().encode())
        self.pose_lines.clear()
        self.rows.seek(0)
        self.rows.truncate()

    def files(self) -> list[tuple[BinaryIO, Path]]:
        found = [(self.poses, self.poses_path), (self.table, self.table_path)]
        return found + ([(self.skips, self.skipped_path)] if self.skips is not None else [])

    def close(self, finished: bool) -> None:
        """Write what is left, sync to disk and close; a finished run's files take their
        final names, a stopped run's stay `.partial` and one line on stderr says where."""
        self.flush()
        for file, _ in self.files():
            os.fsync(file.fileno())
            file.close()
        if finished:
            for _, path in self.files():
                os.replace(partial_of(path), path)
            return
        print(
            f"localize: stopped after {self.written} frames; their answers are in "
            f"{partial_of(self.poses_path)} and {partial_of(self.table_path)}",
            file=sys.stderr,
        )


def write_all(file: BinaryIO, data: bytes) -> None:
    """All of `data` to an unbuffered file (a raw write may take only part of it)."""
    view = memoryview(data)
    while view:
        view = view[file.write(view) or 0 :]


def partial_of(path: Path) -> Path:
    """Where `path` is written until the run finishes."""
    return path.with_name(path.name + PARTIAL_SUFFIX)
