"""task=localize: poses of new images from a saved model (localize.model, localize.images).

The model file brings its network, map, crop search and query options; each query.*
value that is set (not null) replaces the file's. The network runs on the configured
engine (relocfw.app.engines), its graphs cached beside the model file.
"""

from __future__ import annotations

import csv
import glob
import io
import re
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
from relocfw.model.checkpoints import write_text_atomic
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


def localize_images(
    relocalizer: Relocalizer, images: list[Path], run_dir: Path, quiet: bool = False
) -> list[Localization]:
    """Localize every image; write poses.txt (TUM format) and localization.csv."""
    progress = Progress(len(images), "localizing", quiet=quiet)
    answers = []
    # Any object with `localize` works; a Relocalizer's options say how many at once.
    options = getattr(relocalizer, "options", None)
    group = getattr(options, "queries_at_once", 1)
    # A refiner that reads a query's recording (refine=sequence) gets each image's
    # folder as its recording and the images in the order given (sorted by name).
    refined = getattr(relocalizer, "refiner", None) is not None
    for start in range(0, len(images), group):
        # Images are read a group at a time, so memory stays flat however many.
        paths = images[start : start + group]
        pixels = [read_rgb(path) for path in paths]
        names = [f"{path.parent.name}/{path.stem}" for path in paths]
        if group == 1 and refined:
            answers.append(relocalizer.localize(pixels[0], name=names[0]))
        elif group == 1:
            answers.append(relocalizer.localize(pixels[0]))
        elif refined:
            answers += relocalizer.localize_many(pixels, group, names=names)
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
