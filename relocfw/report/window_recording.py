"""Every window of every diagnosed query, as a file: selection rules run offline on it.

`task=diagnose` writes `diagnose_windows.npz`: per crop offset its window, map distance
and regressed pose, its nearest map images (by descriptor), and per query the ground
truth; per map image its pose. Any test-time selection rule
(relocfw.core.window_rules) is then evaluated from the file without rerunning the
network. The file holds numbers only (numpy's format, read with allow_pickle=False).
"""

from __future__ import annotations

import zipfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocfw.core.atomic_files import atomic_write
from relocfw.core.errors import DataError
from relocfw.core.values import Pose
from relocfw.core.window_rules import Windows, along_axis
from relocfw.report.diagnosis import QueryWindows, pose_errors

FORMAT = 1
REQUIRED = (
    "format",
    "frames",
    "starts",
    "views",
    "distances",
    "positions",
    "quaternions",
    "centres",
    "truth_positions",
    "truth_quaternions",
    "map_positions",
    "map_quaternions",
    "distance_scale",
)


@dataclass(frozen=True)
class RecordedQuery:
    """One query's distinct windows as a rule sees them, and its ground truth."""

    frame: str
    windows: Windows
    truth: Pose

    def errors(self, position: np.ndarray, quaternion: np.ndarray) -> tuple[float, float]:
        """Position (m) and orientation (deg) error of an answer; inf if not finite."""
        p, o = pose_errors(np.asarray(position)[None], np.asarray(quaternion)[None], self.truth)
        return float(p[0]), float(o[0])

    def window_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """[n] each window's position and orientation error."""
        return pose_errors(self.windows.positions, self.windows.quaternions, self.truth)


def save_windows(path: Path, queries: Sequence[QueryWindows], map_poses: Sequence[Pose]) -> None:
    """Write the diagnosed queries (with their poses and neighbours) atomically."""
    if not queries or any(q.positions is None or q.truth is None for q in queries):
        raise ValueError("save_windows needs queries diagnosed with their poses")
    recorded = all(q.neighbours is not None for q in queries)
    lengths = [len(q.distances) for q in queries]
    arrays = {
        "format": np.array(FORMAT),
        "frames": np.array([q.frame for q in queries]),
        "starts": np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        "views": np.concatenate([q.views for q in queries]),
        "distances": np.concatenate([q.distances for q in queries]),
        "positions": np.concatenate([q.positions for q in queries]),
        "quaternions": np.concatenate([q.quaternions for q in queries]),
        "centres": np.array([q.centre for q in queries], dtype=np.int64),
        "truth_positions": np.stack([q.truth.position for q in queries]),
        "truth_quaternions": np.stack([q.truth.quaternion for q in queries]),
        "map_positions": np.array([p.position for p in map_poses]).reshape(-1, 3),
        "map_quaternions": np.array([p.quaternion for p in map_poses]).reshape(-1, 4),
        "distance_scale": np.array(queries[0].distance_scale),
    }
    if recorded:
        arrays["neighbours"] = np.concatenate([q.neighbours for q in queries]).astype(np.int64)
    with atomic_write(Path(path)) as stream:
        np.savez_compressed(stream, **arrays)


def distinct_windows(views: np.ndarray) -> np.ndarray:
    """Entry of each distinct window, in offset order (offsets may share one)."""
    _, first = np.unique(np.round(views, 6), axis=0, return_index=True)
    return np.sort(first)


def load_windows(path: Path) -> list[RecordedQuery]:
    """The recorded queries of a `diagnose_windows.npz`, each window once.

    Raises:
        DataError: naming the file, when it is missing, not such a file, or of
            another format.
    """
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
        if not hasattr(data, "files"):  # a .npy holds one array, not an archive of them
            raise ValueError("a single array, not an .npz archive")
        with data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as error:
        raise DataError(f"{path}: not a readable diagnose_windows.npz ({error})") from error
    missing = [key for key in REQUIRED if key not in arrays]
    if missing:
        raise DataError(f"{path}: not a diagnose_windows.npz (missing {', '.join(missing)})")
    if int(arrays["format"]) != FORMAT:
        raise DataError(f"{path}: format {int(arrays['format'])}, this relocfw reads {FORMAT}")
    neighbours = arrays.get("neighbours")
    starts = arrays["starts"]
    queries = []
    for q, frame in enumerate(arrays["frames"]):
        part = slice(int(starts[q]), int(starts[q + 1]))
        views = arrays["views"][part]
        keep = distinct_windows(views)
        # The centre offset's window (it may share one with an earlier offset).
        centre = int(np.argmin(np.abs(views[keep] - views[arrays["centres"][q]]).sum(axis=1)))
        offsets = along_axis(views[keep, 0] + views[keep, 1])  # it moves along one axis
        near = None if neighbours is None else neighbours[part][keep]
        windows = Windows(
            distances=arrays["distances"][part][keep],
            positions=arrays["positions"][part][keep],
            quaternions=arrays["quaternions"][part][keep],
            offsets=offsets,
            centre=centre,
            distance_scale=float(arrays["distance_scale"]),
            neighbour_positions=None if near is None else arrays["map_positions"][near],
            neighbour_quaternions=None if near is None else arrays["map_quaternions"][near],
        )
        truth = Pose(arrays["truth_positions"][q], arrays["truth_quaternions"][q])
        queries.append(RecordedQuery(str(frame), windows, truth))
    return queries
