"""Microsoft 7-Scenes layout: seq-XX/frame-NNNNNN.color.{png,jpg} + .pose.txt.

Each frame also gets its camera and, where the folder has it, its depth map:
    camera      K of `camera-intrinsics.txt` in the scene folder, else in the dataset
                root (the folder above it, where 7-Scenes' archives put it), sized like
                the first image of the split; without either file, 7-Scenes' nominal
                Kinect camera (585, 585, 320, 240 for 640 x 480), without reading an
                image (so a copy scaled to another size needs its own file), with one
                note on stderr naming the folder and the values.
    depth_path  `frame-NNNNNN.depth.png` beside the colour image when it exists (16-bit,
                millimetres; copies without depth load as before, with None).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from relocfw.core.camera import SEVENSCENES_DEFAULT, PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import pose_from_matrix
from relocfw.core.values import Pose
from relocfw.data.depth import depth_path_of
from relocfw.data.frames import Frame
from relocfw.data.intrinsics import INTRINSICS_FILE, note_default_camera, read_camera_for_images
from relocfw.data.on_error import OnError

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


def split_text(path: Path) -> str:
    """A split file's text; a byte that is not UTF-8 is a DataError naming the file
    and the byte's position (the file is likely damaged or not a split file)."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise DataError(
            f"{path}: not a text split file (byte {error.object[error.start]:#04x} at "
            f"offset {error.start} is not UTF-8)"
        ) from error


def read_split(path: Path) -> list[int]:
    """Sequence numbers listed in a TrainSplit.txt / TestSplit.txt file."""
    if not path.is_file():
        raise DataError(f"split file not found: {path}")
    numbers = []
    for number, line in enumerate(split_text(path).splitlines(), start=1):
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
        values = [float(v) for v in path.read_text(encoding="utf-8").split()]
    except ValueError as error:  # UnicodeDecodeError included: it is a ValueError
        raise DataError(f"{path}: not a pose file ({error})") from error
    if len(values) != 16:
        raise DataError(f"{path}: expected 16 numbers (a 4x4 matrix), found {len(values)}")
    return np.array(values).reshape(4, 4)


def intrinsics_file(folder: Path) -> Path | None:
    """The camera-intrinsics.txt of a scene folder: its own, else the dataset root's.

    7-Scenes' archives keep one file for all scenes in the folder holding the scene
    folders; a file in the scene folder itself is more specific, so it wins.
    """
    for candidate in (folder / INTRINSICS_FILE, folder.parent / INTRINSICS_FILE):
        if candidate.is_file():
            return candidate
    return None


def scene_camera(folder: Path, images: Sequence[Path]) -> PinholeCamera:
    """The camera of a scene's images: its intrinsics file's, else 7-Scenes' default.

    Args:
        folder: the scene folder.
        images: the colour images of the split, in order (the first that decodes
            gives the size a file's matrix belongs to).

    Raises:
        DataError: naming the intrinsics file when it is malformed.
    """
    path = intrinsics_file(folder)
    if path is None:
        note_default_camera(folder, SEVENSCENES_DEFAULT, "7-Scenes' nominal Kinect intrinsics")
        return SEVENSCENES_DEFAULT
    return read_camera_for_images(path, images)


def existing_depth(image: Path) -> Path | None:
    """The depth map beside a colour image, or None when there is none."""
    path = depth_path_of(image)
    return path if path.is_file() else None


def sequence_images(seq_dir: Path, source: str) -> list[Path]:
    """The colour images of one sequence folder in frame order (PNG, else JPEG).

    Args:
        seq_dir: `seq-XX`.
        source: what named the sequence (the split file or the option), for errors.
    """
    if not seq_dir.is_dir():
        raise DataError(f"{source}: sequence folder not found: {seq_dir}")
    images = sorted(seq_dir.glob("frame-*.color.png")) or sorted(seq_dir.glob("frame-*.color.jpg"))
    if not images:
        raise DataError(f"no frame-*.color.png or .jpg images in {seq_dir}")
    return images


def load_sevenscenes(
    root: str | Path,
    scene: str | None,
    split: str,
    on_error: OnError | None = None,
    sequences: Sequence[int] | None = None,
) -> list[Frame]:
    """Frames of one split, in sequence then frame order, with camera and depth path.

    Args:
        root: dataset folder (the one holding scene folders), or a scene folder.
        scene: scene name such as "chess"; None when `root` is the scene folder.
        split: "train" or "test".
        on_error: what to do with a bad pose file (default: fail).
        sequences: sequence numbers to use instead of the split file's, e.g. to hold
            out a validation block of the training sequences.

    Raises:
        DataError: a missing split file, sequence folder or image set, a bad pose file
            (under on_error=fail), or a malformed camera-intrinsics.txt (always: it
            concerns every frame), each naming the file.
    """
    on_error = on_error or OnError()
    if split not in SPLIT_FILES:
        raise ConfigError(f"split must be 'train' or 'test', got {split!r}")
    folder = scene_folder(root, scene)
    source = f"dataset.{split}_sequences"
    if sequences is None:
        source = str(folder / SPLIT_FILES[split])
        sequences = read_split(folder / SPLIT_FILES[split])
    posed: list[tuple[str, Path, Pose]] = []
    for sequence in sequences:
        seq_dir = folder / f"seq-{sequence:02d}"
        for image in sequence_images(seq_dir, source):
            stem = image.name.split(".")[0]
            pose_path = seq_dir / f"{stem}.pose.txt"
            try:
                pose = pose_from_matrix(read_pose_file(pose_path), source=str(pose_path))
            except DataError as error:
                on_error.handle(error)
                continue
            posed.append((f"{seq_dir.name}/{stem}", image, pose))
    if not posed:  # every pose skipped: nothing to give a camera to
        return []
    # One camera for the scene: 7-Scenes' frames all come from one Kinect.
    camera = scene_camera(folder, [image for _, image, _ in posed])
    return [
        Frame(name, image, pose, camera=camera, depth_path=existing_depth(image))
        for name, image, pose in posed
    ]


class SevenScenes:
    """A 7-Scenes scene as a dataset: `root/scene` with its split files.

    Args:
        root: the folder holding scene folders (or the scene folder, with scene=None).
        scene: scene name, e.g. "chess".
        on_error: "fail" or "skip" (bad files left out and listed).
        train_sequences: sequence numbers that replace TrainSplit.txt (None: the file).
        test_sequences: sequence numbers that replace TestSplit.txt (None: the file).
    """

    def __init__(
        self,
        root: str | None = None,
        scene: str | None = None,
        on_error: str = "fail",
        train_sequences: Sequence[int] | None = None,
        test_sequences: Sequence[int] | None = None,
    ) -> None:
        self.folder = scene_folder(root, scene)
        self.on_error = OnError(on_error)
        self.sequences = {
            "train": checked_sequences("train_sequences", train_sequences),
            "test": checked_sequences("test_sequences", test_sequences),
        }
        if train_sequences is not None or test_sequences is not None:
            # The effective lists, a split file standing in for the list not given.
            train = self.sequences["train"] or read_split(self.folder / SPLIT_FILES["train"])
            test = self.sequences["test"] or read_split(self.folder / SPLIT_FILES["test"])
            if set(train) & set(test):
                raise ConfigError(
                    f"dataset.train_sequences / dataset.test_sequences: train {train} and "
                    f"test {test} share {sorted(set(train) & set(test))}: a test frame "
                    "would be in the map"
                )

    def frames(self, split: str) -> list[Frame]:
        return load_sevenscenes(self.folder, None, split, self.on_error, self.sequences.get(split))

    def split_source(self, split: str) -> str:
        """What lists the split's frames, for messages: the option or the split file."""
        chosen = self.sequences.get(split)
        if chosen is not None:
            return f"dataset.{split}_sequences={chosen} in {self.folder}"
        return str(self.folder / SPLIT_FILES[split])


def checked_sequences(key: str, values: Sequence[int] | None) -> list[int] | None:
    """A non-empty list of positive sequence numbers, or None (use the split file)."""
    if values is None:
        return None
    if isinstance(values, (str, int)) or not values:
        raise ConfigError(f"dataset.{key} must be a non-empty list such as [1, 3], got {values!r}")
    numbers = []
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"dataset.{key}: sequence numbers are integers >= 1, got {value!r}")
        numbers.append(value)
    return numbers
