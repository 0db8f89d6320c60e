"""Microsoft 7-Scenes layout: seq-XX/frame-NNNNNN.color.{png,jpg} + .pose.txt."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from relocfw.data.frames import Frame
from relocfw.data.on_error import OnError
from relocfw.errors import ConfigError, DataError
from relocfw.geometry import pose_from_matrix

SPLIT_FILES = {"train": "TrainSplit.txt", "test": "TestSplit.txt"}
SEQUENCE_LINE = re.compile(r"^sequence(\d+)$", re.IGNORECASE)


def scene_folder(root: str | Path, scene: str | None) -> Path:
    """The folder holding the split files: `root/scene`, or `root` itself."""
    if root is None or str(root) == "":
        raise ConfigError("dataset.root is not set: pass dataset.root=DIR")
    root = Path(root).expanduser()
    if not root.is_dir():
        raise DataError(f"dataset.root: folder not found: {root}")
    folder = root / scene if scene else root
    if not folder.is_dir():
        available = sorted(p.name for p in root.iterdir() if (p / "TrainSplit.txt").is_file())
        raise DataError(
            f"dataset.scene: no scene {scene!r} in {root}"
            + (f" (found: {', '.join(available)})" if available else "")
        )
    return folder


def read_split(path: Path) -> list[int]:
    """Sequence numbers listed in a TrainSplit.txt / TestSplit.txt file."""
    if not path.is_file():
        raise DataError(f"split file not found: {path}")
    numbers = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.strip()
        if not text:
            continue
        match = SEQUENCE_LINE.match(text)
        if not match:
            raise DataError(f"{path}:{number}: expected a line like 'sequence1', got {text!r}")
        numbers.append(int(match.group(1)))
    if not numbers:
        raise DataError(f"{path}: lists no sequences")
    return numbers


def read_pose_file(path: Path) -> np.ndarray:
    """A 4x4 matrix from 7-Scenes' text format (tabs, CRLF, 3-digit exponents)."""
    if not path.is_file():
        raise DataError(f"pose file not found: {path}")
    try:
        values = [float(v) for v in path.read_text().split()]
    except ValueError as error:
        raise DataError(f"{path}: not a pose file ({error})") from error
    if len(values) != 16:
        raise DataError(f"{path}: expected 16 numbers (a 4x4 matrix), found {len(values)}")
    return np.array(values).reshape(4, 4)


def load_sevenscenes(
    root: str | Path, scene: str | None, split: str, on_error: OnError | None = None
) -> list[Frame]:
    """Frames of one split, in sequence then frame order.

    Args:
        root: dataset folder (the one holding scene folders), or a scene folder.
        scene: scene name such as "chess"; None when `root` is the scene folder.
        split: "train" or "test".
        on_error: what to do with a bad pose file (default: fail).
    """
    on_error = on_error or OnError()
    if split not in SPLIT_FILES:
        raise ConfigError(f"split must be 'train' or 'test', got {split!r}")
    folder = scene_folder(root, scene)
    frames = []
    for sequence in read_split(folder / SPLIT_FILES[split]):
        seq_dir = folder / f"seq-{sequence:02d}"
        if not seq_dir.is_dir():
            raise DataError(f"{folder / SPLIT_FILES[split]}: sequence folder not found: {seq_dir}")
        images = sorted(seq_dir.glob("frame-*.color.png")) or sorted(
            seq_dir.glob("frame-*.color.jpg")
        )
        if not images:
            raise DataError(f"no frame-*.color.png or .jpg images in {seq_dir}")
        for image in images:
            stem = image.name.split(".")[0]
            pose_path = seq_dir / f"{stem}.pose.txt"
            try:
                pose = pose_from_matrix(read_pose_file(pose_path), source=str(pose_path))
            except DataError as error:
                on_error.handle(error)
                continue
            frames.append(Frame(f"{seq_dir.name}/{stem}", image, pose))
    return frames


class SevenScenes:
    """A 7-Scenes scene as a dataset: `root/scene` with its split files.

    Args:
        root: the folder holding scene folders (or the scene folder, with scene=None).
        scene: scene name, e.g. "chess".
        on_error: "fail" or "skip" (bad files left out and listed).
    """

    def __init__(
        self, root: str | None = None, scene: str | None = None, on_error: str = "fail"
    ) -> None:
        self.folder = scene_folder(root, scene)
        self.on_error = OnError(on_error)

    def frames(self, split: str) -> list[Frame]:
        return load_sevenscenes(self.folder, None, split, self.on_error)
