"""`relocfw task=localize`: poses of new images from a saved model."""

from __future__ import annotations

import csv
import glob
import io
import re
from pathlib import Path

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import read_rgb
from relocfw.core.pipeline import Relocalizer
from relocfw.core.progress import Progress
from relocfw.core.values import Localization
from relocfw.model.checkpoints import write_text_atomic
from relocfw.report.evaluation import ANSWER_COLUMNS, POSE_COLUMNS, answer_cells

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
COLUMNS = ("image", "timestamp", *POSE_COLUMNS, *ANSWER_COLUMNS)


def find_images(pattern: str) -> list[Path]:
    """Images named by a file, a folder (every image in it) or a glob pattern."""
    if not pattern:
        raise ConfigError("images is not set: pass images=FILE, images=DIR or images='DIR/*.png'")
    path = Path(pattern).expanduser()
    if path.is_dir():
        found = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    elif path.is_file():
        found = [path]
    else:
        found = sorted(Path(p) for p in glob.glob(str(path)))
    if not found:
        raise DataError(f"images={pattern}: no image files found")
    return found


TIMESTAMP_NAME = re.compile(r"\d+(\.\d+)?")


def timestamp_of(path: Path, position: int) -> str:
    """The file name's number when it is one (TUM names images by time), else its index.

    Only plain decimals count (digits, one optional fraction): `float` would also take
    names such as "nan", "inf" or "1_000", which TUM tools cannot read back.
    """
    return path.stem if TIMESTAMP_NAME.fullmatch(path.stem) else str(position)


def localize_images(
    relocalizer: Relocalizer, images: list[Path], run_dir: Path, quiet: bool = False
) -> list[Localization]:
    """Localize every image; write poses.txt (TUM format) and localization.csv."""
    progress = Progress(len(images), "localizing", quiet=quiet)
    answers = []
    # Any object with `localize` works; a Relocalizer's options say how many at once.
    options = getattr(relocalizer, "options", None)
    group = getattr(options, "queries_at_once", 1)
    for start in range(0, len(images), group):
        # Images are read a group at a time, so memory stays flat however many.
        pixels = [read_rgb(path) for path in images[start : start + group]]
        if group == 1:
            answers.append(relocalizer.localize(pixels[0]))
        else:
            answers += relocalizer.localize_many(pixels, group)
        progress.advance(len(pixels))
    progress.close()
    tum_lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world)"]
    table = io.StringIO()
    writer = csv.writer(table)
    writer.writerow(COLUMNS)
    for position, (path, answer) in enumerate(zip(images, answers, strict=True)):
        stamp = timestamp_of(path, position)
        (x, y, z), (qw, qx, qy, qz) = answer.pose.position, answer.pose.quaternion
        tum_lines.append(" ".join([stamp] + [f"{v:.9f}" for v in (x, y, z, qx, qy, qz, qw)]))
        writer.writerow(
            [str(path), stamp]
            + [f"{v:.9f}" for v in (x, y, z, qw, qx, qy, qz)]
            + answer_cells(answer)
        )
    write_text_atomic("\n".join(tum_lines) + "\n", Path(run_dir) / "poses.txt")
    write_text_atomic(table.getvalue(), Path(run_dir) / "localization.csv")
    print(
        f"{len(answers)} images localized: {Path(run_dir) / 'poses.txt'}, "
        f"{Path(run_dir) / 'localization.csv'}"
    )
    return answers
