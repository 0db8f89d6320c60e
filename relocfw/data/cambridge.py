"""Cambridge Landmarks: `dataset_train.txt` / `dataset_test.txt`, `path x y z w p q r`.

The three header lines are skipped. The position is the camera centre in the world;
the quaternion (w first) is the world-to-camera rotation, so the camera-to-world
rotation relocfw uses is its conjugate.
"""

from __future__ import annotations

from pathlib import Path

from relocfw.core.errors import DataError
from relocfw.core.geometry import checked_quaternion, conjugate
from relocfw.core.values import Pose
from relocfw.data.frames import Frame, claim_frame_name
from relocfw.data.on_error import OnError
from relocfw.data.sevenscenes import scene_folder
from relocfw.data.text import data_lines, numbers

SPLIT_FILES = {"train": "dataset_train.txt", "test": "dataset_test.txt"}
HEADER_LINES = 3


def cambridge_pose(values: list[float], source: str) -> Pose:
    """Camera-to-world pose of one line's `x y z w p q r`."""
    world_to_camera = checked_quaternion(values[3:], source)
    return Pose(values[:3], conjugate(world_to_camera))


def load_cambridge(folder: Path, split: str, on_error: OnError | None = None) -> list[Frame]:
    on_error = on_error or OnError()
    frames = []
    claimed: dict[str, Path] = {}
    for source, fields in data_lines(folder / SPLIT_FILES[split], skip=HEADER_LINES):
        try:
            if len(fields) != 8:
                raise DataError(
                    f"{source}: expected 'path x y z w p q r', found {len(fields)} values"
                )
            pose = cambridge_pose(numbers(fields[1:], source, 7), source)
            image = fields[0]
            name = str(Path(image).with_suffix(""))
            claim_frame_name(claimed, name, folder / image, source)
        except DataError as error:
            on_error.handle(error)
            continue
        frames.append(Frame(name, folder / image, pose))
    return frames


class CambridgeLandmarks:
    """A Cambridge Landmarks scene: `root/scene` with its dataset_*.txt files.

    Args:
        root: folder holding scene folders (or the scene folder, with scene=None).
        scene: e.g. "KingsCollege".
        on_error: "fail" or "skip" (bad lines left out and listed).
    """

    def __init__(self, root: str | None = None, scene: str | None = None, on_error: str = "fail"):
        self.folder = scene_folder(root, scene)
        self.on_error = OnError(on_error)

    def frames(self, split: str) -> list[Frame]:
        return load_cambridge(self.folder, split, self.on_error)

    def split_source(self, split: str) -> str:
        """What lists the split's frames, for messages: its dataset_*.txt file."""
        return str(self.folder / SPLIT_FILES[split])
