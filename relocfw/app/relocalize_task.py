"""The CLI's tasks as plain functions: objects and paths in, files and summaries out."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from relocfw.core.errors import DataError
from relocfw.core.interfaces import Backbone
from relocfw.core.json_output import strict_json
from relocfw.core.pipeline import Relocalizer
from relocfw.data.frames import Frame, mean_pose, read_good_images
from relocfw.data.on_error import OnError
from relocfw.model.checkpoints import CHECKPOINT_FORMAT, settings_key, write_text_atomic
from relocfw.model.distributed import World
from relocfw.model.training import TrainingImages, TrainingRun, TrainSettings, train_backbone
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.report.evaluation import (
    MethodResult,
    constant_answer,
    evaluate,
    per_image_csv,
    summarise,
)
from relocfw.report.table import format_table
from relocfw.report.units import METRES, PositionUnit, json_note, relabel_row, text_note

BASELINES = ("mean_pose", "posenet")


class Dataset(Protocol):
    def frames(self, split: str) -> list[Frame]: ...


def load_split(dataset: Dataset, split: str, quiet: bool) -> tuple[list[Frame], list[np.ndarray]]:
    """Frames and decoded images of a split; bad ones follow the dataset's on_error."""
    frames = dataset.frames(split)
    on_error = getattr(dataset, "on_error", None) or OnError()
    frames, images = read_good_images(frames, on_error, f"loading {split} images", quiet)
    if not frames:
        raise DataError(f"the {split} split is empty")
    return frames, images


def write_skipped(dataset: Dataset, run_dir: Path) -> None:
    """List what on_error=skip left out, so nothing is dropped silently."""
    on_error = getattr(dataset, "on_error", None)
    if on_error is not None and on_error.skipped:
        path = Path(run_dir) / "skipped.txt"
        write_text_atomic("\n".join(on_error.skipped) + "\n", path)
        print(f"skipped {len(on_error.skipped)} bad entries (dataset.on_error=skip): {path}")


def frames_fingerprint(frames: Sequence[Frame]) -> str:
    """Changes when the training images' names or poses change, so stale models are not reused."""
    rows = [
        (f.name, np.round(f.pose.position, 6).tolist(), np.round(f.pose.quaternion, 6).tolist())
        for f in frames
    ]
    return settings_key({"frames": rows})


def train_or_reuse(
    backbone: Backbone,
    frames: Sequence[Frame],
    images: Sequence[np.ndarray],
    settings: TrainSettings,
    identity: dict[str, Any],
    cache_dir: Path,
    device: torch.device,
    quiet: bool,
    world: World | None = None,
    log_dir: Path | None = None,
) -> tuple[Path, TrainingRun]:
    """Train the backbone, or load the checkpoint of the same model trained before.

    The checkpoint is named by a hash of the dataset and backbone settings, the
    training settings and the training frames themselves.

    Returns:
        The checkpoint path, and how training went (reused, resumed or fresh).
    """
    key = settings_key(
        {
            "format": CHECKPOINT_FORMAT,
            "identity": identity,
            "train": settings.__dict__,
            "frames": frames_fingerprint(frames),
        }
    )
    checkpoint = Path(cache_dir).expanduser() / "checkpoints" / f"{key}.pt"
    data = TrainingImages(
        images, [f.pose for f in frames], backbone.input_size, settings.crop_scale
    )
    run = train_backbone(backbone, data, settings, checkpoint, key, device, quiet, world, log_dir)
    return checkpoint, run


def run_method(
    method: str,
    relocalizer: Relocalizer,
    train: tuple[Sequence[Frame], Sequence[np.ndarray]],
    test: tuple[Sequence[Frame], Sequence[np.ndarray]],
    quiet: bool = False,
) -> tuple[MethodResult, np.ndarray]:
    """Fit the map on the training split and relocalize the test split.

    Returns:
        The method's answers and the map's [N, D] training descriptors.
    """
    features = relocalizer.fit(train[1], [f.pose for f in train[0]], quiet=quiet)
    return evaluate(method, relocalizer, *test, quiet=quiet), features


def summary_csv(summaries: Sequence[dict[str, Any]]) -> str:
    """One row per method, one column per summary key (metrics, shares and costs)."""
    stream = io.StringIO()
    # Sampled methods carry extra uncertainty columns: the union, in first-seen order.
    fields = list(dict.fromkeys(key for summary in summaries for key in summary))
    writer = csv.DictWriter(stream, fieldnames=fields, restval="")
    writer.writeheader()
    writer.writerows(summaries)
    return stream.getvalue()


def write_results(
    results: Sequence[MethodResult], run_dir: Path, name: str = "", unit: PositionUnit = METRES
) -> str:
    """results{name}.csv (per query), summary{name}.json and .csv (per method) and
    table{name}.txt; returns the table.

    Each file names the positions' unit as it is written: table{name}.txt starts with
    the unit's note, every summary row (JSON and CSV) carries it as `units_note`, and
    results{name}.csv has the unit in its column names. Files from earlier runs in
    `run_dir` are replaced, never annotated.
    """
    summaries = [summarise(r) for r in results]
    rows = [relabel_row(summary, unit) | json_note(unit) for summary in summaries]
    run_dir = Path(run_dir)
    write_text_atomic(per_image_csv(results, unit), run_dir / f"results{name}.csv")
    write_text_atomic(strict_json(rows), run_dir / f"summary{name}.json")
    write_text_atomic(summary_csv(rows), run_dir / f"summary{name}.csv")
    table = format_table(summaries, unit)
    write_text_atomic(text_note(unit) + table + "\n", run_dir / f"table{name}.txt")
    return table


def relocalize(
    relocalizer: Relocalizer,
    method: str,
    train: tuple[Sequence[Frame], Sequence[np.ndarray]],
    test: tuple[Sequence[Frame], Sequence[np.ndarray]],
    run_dir: Path,
    baselines: Sequence[str] = BASELINES,
    centre_label: str = "posenet (centre crop)",
    quiet: bool = False,
    unit: PositionUnit = METRES,
) -> list[MethodResult]:
    """The main job after training: the method and its baselines, results written
    with the positions' `unit` (relocfw.report.units.unit_of the dataset)."""
    results = []
    if "mean_pose" in baselines:
        results.append(constant_answer("mean training pose", mean_pose(train[0]), test[0]))
    method_result, _ = run_method(method, relocalizer, train, test, quiet)
    if "posenet" in baselines and not (
        isinstance(relocalizer.crop, CentreCrop) and relocalizer.retrieval_k == 0
    ):
        # PoseNet: the centre crop of the same network and map, sampled as the method's
        # network is (backbone.mc_samples), with its seed; no random crops.
        centre = Relocalizer(
            relocalizer.backbone,
            relocalizer.index,
            CentreCrop(),
            relocalizer.device,
            relocalizer.batch_size,
            sample_seed=relocalizer.sample_seed,
            queries_at_once=relocalizer.queries_at_once,
        )
        # The map is already fitted; only the queries run again.
        results.append(evaluate(centre_label, centre, *test, quiet=quiet))
    results.append(method_result)
    print(write_results(results, run_dir, unit=unit))
    print(f"\nresults: {Path(run_dir) / 'results.csv'}, {Path(run_dir) / 'summary.json'}")
    if unit.note:
        print(f"note: {unit.note}")
    return results
