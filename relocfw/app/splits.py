"""A dataset's splits as the tasks read them: frames and decoded images, bad ones
handled by the dataset's on_error and listed in the run directory."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from relocfw.core.errors import DataError
from relocfw.data.frames import Frame, read_good_images
from relocfw.data.on_error import OnError
from relocfw.model.checkpoints import write_text_atomic


class Dataset(Protocol):
    def frames(self, split: str) -> list[Frame]: ...


def load_split(dataset: Dataset, split: str, quiet: bool) -> tuple[list[Frame], list[np.ndarray]]:
    """Frames and decoded images of a split; bad ones follow the dataset's on_error."""
    frames = dataset.frames(split)
    on_error = getattr(dataset, "on_error", None) or OnError()
    frames, images = read_good_images(frames, on_error, f"loading {split} images", quiet)
    if not frames:
        raise DataError(empty_split_message(dataset, split, on_error))
    return frames, images


def empty_split_message(dataset: Dataset, split: str, on_error: OnError) -> str:
    """Names what lists the split (the dataset's `split_source`, where it has one) and
    how many entries on_error=skip left out, so an empty split can be traced."""
    describe = getattr(dataset, "split_source", None)
    named = f"{describe(split)}: " if describe is not None else ""
    skipped = len(on_error.skipped)
    left_out = f" ({skipped} bad entries skipped so far, dataset.on_error=skip)" if skipped else ""
    return f"{named}the {split} split is empty{left_out}"


def write_skipped(dataset: Dataset, run_dir: Path) -> None:
    """List what on_error=skip left out, so nothing is dropped silently."""
    on_error = getattr(dataset, "on_error", None)
    if on_error is not None and on_error.skipped:
        path = Path(run_dir) / "skipped.txt"
        write_text_atomic("\n".join(on_error.skipped) + "\n", path)
        print(f"skipped {len(on_error.skipped)} bad entries (dataset.on_error=skip): {path}")
