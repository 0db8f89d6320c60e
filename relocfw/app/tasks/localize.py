"""task=localize: poses of new images from a saved model (localize.model, localize.images).

The model file brings its network, map, crop search and query options; each query.*
value that is set (not null) replaces the file's. The network runs on the configured
engine (relocfw.app.engines), its graphs cached beside the model file.
"""

from __future__ import annotations

import csv
import glob
import os
import re
import sys
from pathlib import Path

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from relocfw.app.engines import on_engine
from relocfw.app.methods import in_query_terms, query_values
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import read_rgb
from relocfw.core.pipeline import Relocalizer
from relocfw.core.progress import Progress
from relocfw.core.values import Localization
from relocfw.model.distributed import World
from relocfw.model.model_file import load_model
from relocfw.report.evaluation import ANSWER_COLUMNS, POSE_COLUMNS, answer_cells

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
COLUMNS = ("image", "timestamp", *POSE_COLUMNS, *ANSWER_COLUMNS)
TIMESTAMP_NAME = re.compile(r"\d+(\.\d+)?")


def model_file(value: str | None, key: str) -> Path:
    """The model file a task reads, from its config key (localize.model, export.model)."""
    if not value:
        raise ConfigError(f"{key} is not set: pass {key}=FILE (a model.relocfw from a run)")
    return Path(value).expanduser()


def find_images(pattern: str) -> list[Path]:
    """Images named by a file, a folder (every image in it) or a glob pattern."""
    if not pattern:
        raise ConfigError(
            "localize.images is not set: pass localize.images=FILE, localize.images=DIR "
            "or localize.images='DIR/*.png'"
        )
    path = Path(pattern).expanduser()
    if path.is_dir():
        found = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    elif path.is_file():
        found = [path]
    else:
        found = sorted(Path(p) for p in glob.glob(str(path)))
    if not found:
        raise DataError(f"localize.images={pattern}: no image files found")
    # A 7-Scenes or synthetic sequence keeps 16-bit depth maps beside its colour
    # images; read as colour they would be localized as nonsense, not refused.
    depth = [p for p in found if p.name.lower().endswith(".depth.png")]
    if depth:
        raise DataError(
            f"localize.images={pattern}: {len(depth)} of the {len(found)} files are depth "
            f"maps ({depth[0].name}, ...); name the colour images, e.g. "
            f"localize.images='{depth[0].parent}/*.color.png'"
        )
    return found


def timestamp_of(path: Path, position: int) -> str:
    """The file name's number when it is one (TUM names images by time), else its index.

    Only plain decimals count (digits, one optional fraction): `float` would also take
    names such as "nan", "inf" or "1_000", which TUM tools cannot read back.
    """
    return path.stem if TIMESTAMP_NAME.fullmatch(path.stem) else str(position)


PARTIAL_SUFFIX = ".partial"


class AnswerFiles:
    """poses.txt (TUM format) and localization.csv, written one row per answer as it
    is made and flushed.

    The rows go to `poses.txt.partial` and `localization.csv.partial` first: a run
    that stops at image 900 (a crash, a kill, a bad file) keeps the 899 rows before
    it there, and a finished run renames them over the final names, so files a
    previous run left under those names are never replaced by a half-written one.
    """

    def __init__(self, run_dir: Path) -> None:
        self.poses_path = Path(run_dir) / "poses.txt"
        self.table_path = Path(run_dir) / "localization.csv"
        Path(run_dir).mkdir(parents=True, exist_ok=True)
        self.poses = partial_of(self.poses_path).open("w", encoding="utf-8")
        self.table = partial_of(self.table_path).open("w", encoding="utf-8", newline="")
        self.writer = csv.writer(self.table)
        self.written = 0
        self.poses.write("# timestamp tx ty tz qx qy qz qw (camera-to-world)\n")
        self.writer.writerow(COLUMNS)
        self.flush()

    def write(self, path: Path, position: int, answer: Localization) -> None:
        """One image's answer: a line of poses.txt and a row of localization.csv."""
        stamp = timestamp_of(path, position)
        (x, y, z), (qw, qx, qy, qz) = answer.pose.position, answer.pose.quaternion
        self.poses.write(" ".join([stamp] + [f"{v:.9f}" for v in (x, y, z, qx, qy, qz, qw)]))
        self.poses.write("\n")
        self.writer.writerow(
            [str(path), stamp]
            + [f"{v:.9f}" for v in (x, y, z, qw, qx, qy, qz)]
            + answer_cells(answer)
        )
        self.written += 1

    def flush(self) -> None:
        """Hand what is written to the system: a crash or kill of this process after
        this loses none of it (no fsync per group: that would cost a disk round trip
        per image, and only a power cut needs it)."""
        for file in (self.poses, self.table):
            file.flush()

    def close(self, finished: bool) -> None:
        """Flush, sync to disk and close both files; a finished run's take their final
        names, a stopped run's stay `.partial` and one line on stderr says where."""
        for file in (self.poses, self.table):
            file.flush()
            os.fsync(file.fileno())
            file.close()
        if finished:
            for path in (self.poses_path, self.table_path):
                os.replace(partial_of(path), path)
            return
        print(
            f"localize: stopped after {self.written} images; their answers are in "
            f"{partial_of(self.poses_path)} and {partial_of(self.table_path)}",
            file=sys.stderr,
        )


def partial_of(path: Path) -> Path:
    """Where `path` is written until the run finishes."""
    return path.with_name(path.name + PARTIAL_SUFFIX)


def localize_group(
    relocalizer: Relocalizer, paths: list[Path], group: int, refined: bool
) -> list[Localization]:
    """The answers for one group of images, read here so memory stays flat."""
    pixels = [read_rgb(path) for path in paths]
    names = [f"{path.parent.name}/{path.stem}" for path in paths]
    if group == 1 and refined:
        return [relocalizer.localize(pixels[0], name=names[0])]
    if group == 1:
        return [relocalizer.localize(pixels[0])]
    if refined:
        return relocalizer.localize_many(pixels, group, names=names)
    return relocalizer.localize_many(pixels, group)


def localize_images(
    relocalizer: Relocalizer, images: list[Path], run_dir: Path, quiet: bool = False
) -> list[Localization]:
    """Localize every image; write poses.txt (TUM format) and localization.csv as it
    goes (see AnswerFiles: a run that stops keeps the rows it made, as `.partial`)."""
    progress = Progress(len(images), "localizing", quiet=quiet)
    answers: list[Localization] = []
    # Any object with `localize` works; a Relocalizer's options say how many at once.
    options = getattr(relocalizer, "options", None)
    group = getattr(options, "queries_at_once", 1)
    # A refiner that reads a query's recording (refine=sequence) gets each image's
    # folder as its recording and the images in the order given (sorted by name).
    refined = getattr(relocalizer, "refiner", None) is not None
    files = AnswerFiles(run_dir)
    finished = False
    try:
        for start in range(0, len(images), group):
            paths = images[start : start + group]
            found = localize_group(relocalizer, paths, group, refined)
            for position, (path, answer) in enumerate(zip(paths, found, strict=True), start):
                files.write(path, position, answer)
            files.flush()
            answers += found
            progress.advance(len(paths))
        finished = True
    finally:
        files.close(finished)
        progress.close()
    print(f"{len(answers)} images localized: {files.poses_path}, {files.table_path}")
    return answers


def load_for_localize(cfg: DictConfig, device: torch.device) -> Relocalizer:
    """The model file's Relocalizer with the query.* values that are set, its network
    run by the configured engine (graphs cached beside the model file)."""
    model = model_file(cfg.localize.model, "localize.model")
    try:
        relocalizer = load_model(model, device, query_values(cfg))
    except ConfigError as error:
        raise in_query_terms(error) from error
    return on_engine(cfg, relocalizer, model, device)


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    relocalizer = load_for_localize(cfg, device)
    images = find_images(str(cfg.localize.images or ""))
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    localize_images(relocalizer, images, run_dir, bool(cfg.quiet))
