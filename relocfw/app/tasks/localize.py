"""task=localize: poses of new frames from a saved model (localize.model, localize.images).

The model file brings its network, map, crop search and query options; each query.*
value that is set (not null) replaces the file's. The network runs on the configured
engine (relocfw.app.engines), its graphs cached in cache_dir/graphs/ by the model
file's content (nothing is written beside the model file).

`localize.images` names image files (a file, folder or glob), a video or a ROS bag
(with `localize.topic`); relocfw.data.streams reads each as one stream of frames,
decoded one at a time. Answers are written as they are made (AnswerFiles), so memory
stays flat and a run that stops keeps every pose it made. A frame that cannot be
decoded or whose query is refused (query.max_aspect, query.max_candidates) stops the
run (`localize.on_error=fail`) or is listed in skipped.txt (`localize.on_error=skip`).
"""

from __future__ import annotations

import itertools
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from relocfw.app.answer_files import AnswerFiles
from relocfw.app.config_schema import name_of
from relocfw.app.engines import on_engine
from relocfw.app.methods import in_query_terms, query_values
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import MAX_ASPECT
from relocfw.core.pipeline import Relocalizer
from relocfw.core.progress import Progress
from relocfw.core.values import Localization
from relocfw.data.streams import (
    StreamFrame,
    count_frames,
    file_frames,
    find_images,
    open_frames,
    source_kind,
    timestamp_of,
    within_aspect,
)
from relocfw.model.distributed import World
from relocfw.model.model_file import load_model

ON_ERROR = ("fail", "skip")
# find_images and timestamp_of live in relocfw.data.streams now; importable from here too.
__all__ = [
    "AnswerFiles",
    "LocalizeRun",
    "find_images",
    "load_for_localize",
    "localize_frames",
    "localize_images",
    "model_file",
    "run",
    "timestamp_of",
]


def model_file(value: str | None, key: str) -> Path:
    """The model file a task reads, from its config key (localize.model, export.model)."""
    if not value:
        raise ConfigError(f"{key} is not set: pass {key}=FILE (a model.relocfw from a run)")
    return Path(value).expanduser()


@dataclass
class Waiting:
    """A decoded frame waiting for its group: its name for the refiner and the
    seconds its decoding took."""

    frame: StreamFrame
    name: str
    decode_seconds: float


def refiner_name(frame: StreamFrame, position: int, recording: str | None) -> str:
    """The frame's name for a refiner that reads recordings (refine=sequence): for image
    files their folder and stem, as before; for a stream its own name and position."""
    if recording is None:
        path = Path(frame.name)
        return f"{path.parent.name}/{path.stem}"
    return f"{recording}/{position}"


def localize_group(
    relocalizer: Relocalizer, waiting: list[Waiting], group: int
) -> list[Localization]:
    """The answers for one group of frames."""
    pixels = [w.frame.image for w in waiting]
    names = [w.name for w in waiting]
    refined = getattr(relocalizer, "refiner", None) is not None
    if group == 1 and refined:
        return [relocalizer.localize(pixels[0], name=names[0])]
    if group == 1:
        return [relocalizer.localize(pixels[0])]
    if refined:
        return relocalizer.localize_many(pixels, group, names=names)
    return relocalizer.localize_many(pixels, group)


@dataclass(frozen=True)
class LocalizeRun:
    """What a localize run did: frames answered and frames skipped (their messages are
    in skipped.txt)."""

    localized: int
    skipped: int


def localize_frames(
    relocalizer: Relocalizer,
    frames: Iterable[StreamFrame],
    run_dir: Path,
    quiet: bool = False,
    total: int | None = None,
    on_error: str = "fail",
    recording: str | None = None,
) -> LocalizeRun:
    """Localize every frame as it comes; write poses.txt (TUM format), localization.csv
    and skipped.txt as it goes (see AnswerFiles: a run that stops keeps its rows).

    Args:
        relocalizer: any object with `localize` (and `localize_many` for groups); a
            Relocalizer's options say how many frames at once (queries_at_once).
        frames: in stream order, decoded as they are reached.
        total: frames expected, for the progress bar; None when unknown.
        on_error: "fail": a frame that cannot be decoded, or whose query is refused
            (thinner than query.max_aspect, more windows than query.max_candidates),
            stops the run with one DataError naming it, after the frames before it are
            answered and written; "skip": it is listed in skipped.txt with its message
            and the run goes on.
        recording: the stream's name for a refiner that reads recordings
            (refine=sequence); None for image files, whose folders name theirs.
    """
    if on_error not in ON_ERROR:
        raise ConfigError(f"localize.on_error must be 'fail' or 'skip', got {on_error!r}")
    progress = Progress(total, "localizing", quiet=quiet, unit="frames")
    options = getattr(relocalizer, "options", None)
    group = getattr(options, "queries_at_once", 1)
    max_aspect = getattr(options, "max_aspect", MAX_ASPECT)
    files = AnswerFiles(run_dir)
    waiting: list[Waiting] = []

    def answer(batch: list[Waiting], size: int) -> None:
        """Answer `batch`, `size` queries at once. A query refused after its frame
        was decoded (a DataError: its crop search asks for more than
        query.max_candidates windows, its strip cannot be allocated) is a frame that
        on_error handles, named by the frame; in a group, the group's frames are then
        answered one at a time (the same answers) to tell it from the others."""
        try:
            found = localize_group(relocalizer, batch, size)
        except DataError as error:
            if len(batch) > 1:
                for item in batch:
                    answer([item], 1)
                return
            frame = batch[0].frame
            message = f"{frame.name}: {error}"
            if on_error == "fail":
                raise DataError(message) from error
            files.skip(StreamFrame(frame.name, frame.timestamp, None, message))
            progress.advance(1)
            return
        for item, result in zip(batch, found, strict=True):
            files.write(item.frame, result, 1000.0 * (item.decode_seconds + result.seconds))
        files.flush()
        progress.advance(len(batch))

    def answer_waiting() -> None:
        if waiting:
            answer(waiting, group)
            waiting.clear()

    finished = False
    stream = iter(frames)
    try:
        for position in itertools.count():
            started = time.perf_counter()
            frame = next(stream, None)
            if frame is None:
                break
            frame = within_aspect(frame, max_aspect)  # too thin: a frame on_error handles
            if frame.error is not None or frame.image is None:
                if on_error == "fail":
                    answer_waiting()  # the frames before it keep their rows
                    raise DataError(frame.error or f"{frame.name}: no image")
                files.skip(frame)
                progress.advance(1)
                continue
            name = refiner_name(frame, position, recording)
            waiting.append(Waiting(frame, name, time.perf_counter() - started))
            if len(waiting) == group:
                answer_waiting()
        answer_waiting()
        finished = True
    finally:
        files.close(finished)
        progress.close()
        close = getattr(stream, "close", None)  # a generator: its source (video) released
        if close is not None:
            close()
    print(f"{files.written} frames localized: {files.poses_path}, {files.table_path}")
    if files.skipped:
        print(
            f"localize: {files.skipped} frames could not be decoded and were skipped "
            f"(localize.on_error=skip): {files.skipped_path}",
            file=sys.stderr,
        )
    return LocalizeRun(files.written, files.skipped)


def localize_images(
    relocalizer: Relocalizer,
    images: list[Path],
    run_dir: Path,
    quiet: bool = False,
    on_error: str = "fail",
) -> LocalizeRun:
    """Localize image files in the order given (see localize_frames)."""
    max_aspect = getattr(getattr(relocalizer, "options", None), "max_aspect", MAX_ASPECT)
    frames = file_frames([Path(p) for p in images], max_aspect)
    return localize_frames(relocalizer, frames, run_dir, quiet, len(images), on_error)


def load_for_localize(cfg: DictConfig, device: torch.device) -> Relocalizer:
    """The model file's Relocalizer with the query.* values that are set, its network
    run by the configured engine (graphs cached by the model file's content)."""
    model = model_file(cfg.localize.model, "localize.model")
    try:
        relocalizer = load_model(model, device, query_values(cfg))
    except ConfigError as error:
        raise in_query_terms(error) from error
    return on_engine(cfg, relocalizer, model, device)


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    relocalizer = load_for_localize(cfg, device)
    if relocalizer.bounds is not None:  # written per frame in localization.csv
        print(f"error bounds: {relocalizer.bounds.describe()}")
    dropped = relocalizer.metadata.get("bounds_dropped_for")
    if dropped:
        print(
            f"note: the model file's error bounds are left out: they were calibrated with "
            f"the file's {', '.join(f'query.{key}' for key in dropped)}, which this command "
            "changes (the answers, and so their errors, change with it)",
            file=sys.stderr,
        )
    spec = str(cfg.localize.images or "")
    topic = str(cfg.localize.topic) if cfg.localize.topic else None
    frames = open_frames(spec, topic, relocalizer.options.max_aspect)
    total = count_frames(spec, topic)
    # A stream (video, bag) is one recording, named by its file; image files by folder.
    recording = None if source_kind(spec) == "files" else Path(spec).name
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    on_error = str(name_of(cfg.localize.on_error))
    localize_frames(relocalizer, frames, run_dir, bool(cfg.quiet), total, on_error, recording)
