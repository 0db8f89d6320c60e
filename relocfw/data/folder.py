"""A plain folder: images plus a poses file whose header names the columns.

For poses from COLMAP, a motion-capture system or a robot: one CSV (or whitespace
separated TXT) per split, e.g.

    image,x,y,z,qw,qx,qy,qz
    images/0001.png,1.0,2.0,0.5,1,0,0,0

Columns are found by name (any order, case-insensitive): the image column is
`image`, `file`, `filename` or `path`; positions `x y z` (or `tx ty tz`); the
camera-to-world rotation `qw qx qy qz`. Image paths are relative to the folder.

A `camera-intrinsics.txt` in the folder (7-Scenes' format: K, sized like the first
image) gives every frame its camera, which refine=features needs; without one the
frames have none (no default is guessed). The folder has no depth maps.

Positions are metres only when the poses are metric and in one world frame;
`dataset.metric: false` says they are not, as for COLMAP (relocfw.report.units).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import checked_quaternion
from relocfw.core.values import Pose
from relocfw.data.frames import Frame, claim_frame_name
from relocfw.data.intrinsics import INTRINSICS_FILE, read_camera_for_images
from relocfw.data.on_error import OnError
from relocfw.data.options import metric_option
from relocfw.data.text import data_lines, numbers

# What reports say first when dataset.metric is false (relocfw.report.units.unit_of).
UNITS_NOTE = "positions are in the poses files' own units (dataset.metric=false), not metres"

COLUMN_NAMES = {
    "image": ("image", "file", "filename", "path"),
    "x": ("x", "tx"),
    "y": ("y", "ty"),
    "z": ("z", "tz"),
    "qw": ("qw",),
    "qx": ("qx",),
    "qy": ("qy",),
    "qz": ("qz",),
}


def column_positions(header: list[str], source: str) -> dict[str, int]:
    """Where each needed column is, by name; a missing one is named in the error."""
    lowered = [h.strip().lower() for h in header]
    found = {}
    for column, aliases in COLUMN_NAMES.items():
        matches = [i for i, name in enumerate(lowered) if name in aliases]
        if not matches:
            raise DataError(
                f"{source}: header has no {column!r} column (accepted names: "
                f"{', '.join(aliases)}); found {header}"
            )
        found[column] = matches[0]
    return found


def load_pose_table(path: Path, folder: Path, on_error: OnError | None = None) -> list[Frame]:
    on_error = on_error or OnError()
    # Split at commas only in a CSV: an image path may hold spaces.
    lines = data_lines(path, comma_fields=True)
    try:
        header_source, header = next(lines)
    except StopIteration:
        raise DataError(f"{path}: empty poses file") from None
    columns = column_positions(header, header_source)
    frames = []
    claimed: dict[str, Path] = {}
    for source, fields in lines:
        try:
            if len(fields) != len(header):
                raise DataError(
                    f"{source}: {len(fields)} values, the header names {len(header)} columns"
                    + space_hint(fields, header)
                )
            picked = [fields[columns[c]] for c in ("x", "y", "z", "qw", "qx", "qy", "qz")]
            values = numbers(picked, source, 7)
            pose = Pose(values[:3], checked_quaternion(values[3:], source))
            image = fields[columns["image"]]
            name = str(Path(image).with_suffix(""))
            claim_frame_name(claimed, name, folder / image, source)
        except DataError as error:
            on_error.handle(error)
            continue
        frames.append(Frame(name, folder / image, pose))
    return frames


def space_hint(fields: list[str], header: list[str]) -> str:
    """Why a line may have more values than columns: a space in an image path of a
    whitespace-separated file ("" where the count is not too high)."""
    if len(fields) <= len(header):
        return ""
    return (
        " (an image path with a space? in a whitespace-separated file a space splits "
        'the path; use a CSV file with commas, quoting the path if needed: "a b.png",1,...)'
    )


class PoseFolder:
    """Images + one poses file per split.

    Args:
        root: the folder; image paths in the poses files are relative to it.
        train: poses file of the map images (default train.csv).
        test: poses file of the query images (default test.csv).
        on_error: "fail" or "skip" (bad lines left out and listed).
        metric: whether the poses are metres in one world frame; False makes reports
            say model units, as COLMAP's option does.

    Attributes:
        metric: read by relocfw.report.units.unit_of.
        units_note: one line for the reports of a non-metric run; "" when metric.
    """

    metric: bool = True
    units_note: str = ""

    def __init__(
        self,
        root: str | None = None,
        train: str = "train.csv",
        test: str = "test.csv",
        on_error: str = "fail",
        metric: bool = True,
    ) -> None:
        self.metric = metric_option(metric)
        self.units_note = "" if self.metric else UNITS_NOTE
        if root is None:
            raise ConfigError("dataset.root is not set: pass dataset.root=DIR")
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise DataError(f"dataset.root: folder not found: {self.root}")
        self.files = {"train": train, "test": test}
        self.on_error = OnError(on_error)

    def frames(self, split: str) -> list[Frame]:
        frames = load_pose_table(self.root / self.files[split], self.root, self.on_error)
        intrinsics = self.root / INTRINSICS_FILE
        if not frames or not intrinsics.is_file():
            return frames
        camera = read_camera_for_images(intrinsics, [f.image_path for f in frames])
        return [replace(frame, camera=camera) for frame in frames]

    def split_source(self, split: str) -> str:
        """What lists the split's frames, for messages: its poses file."""
        return str(self.root / self.files[split])
