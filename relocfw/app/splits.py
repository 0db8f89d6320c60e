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
        raise DataError(f"the {split} split is empty")
    return frames, images


def write_skipped(dataset: Dataset, run_dir: Path) -> None:
    """List what on_error=skip left out, so nothing is dropped silently."""
    on_error = getattr(dataset, "on_error", None)
    if on_error is not None and on_error.skipped:
        path = Path(run_dir) / "skipped.txt"
        write_text_atomic("\n".join(on_error.skipped) + "\n", path)
        print(f"skipped {len(on_error.skipped)} bad entries (dataset.on_error=skip): {path}")
