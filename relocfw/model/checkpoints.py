"""Checkpoint files: named by what produced them, written atomically."""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import torch

from relocfw.core.errors import DataError

# Bump when the layout of saved models changes: it is part of every checkpoint's key,
# so an old checkpoint is never picked up by code that cannot read it.
CHECKPOINT_FORMAT = 3


def settings_key(settings: dict[str, Any]) -> str:
    """Short stable hash of everything that determines a trained model."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@contextmanager
def atomic_write(path: Path, mode: str = "wb") -> Iterator[IO]:
    """A stream to a temporary file beside `path`, renamed over it when the block ends.

    A kill mid-write leaves the previous file intact, never a truncated one; an
    exception removes the temporary. Every file relocfw writes for the user goes
    through here: checkpoints, model files, results, figures.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, mode, **({} if "b" in mode else {"newline": ""})) as stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def save_atomic(payload: dict[str, Any], path: Path) -> None:
    """torch.save `payload` to `path` atomically."""
    with atomic_write(path, "wb") as stream:
        torch.save(payload, stream)


def read_torch_file(path: Path, what: str) -> Any:
    """Tensors saved with torch.save, loaded safely (no pickled code) onto the CPU.

    Args:
        path: the file.
        what: how to name it in an error, e.g. "checkpoint" or "backbone.weights".
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{what}: file not found: {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a damaged file
        raise DataError(f"{what}: cannot read {path}: {error}") from error


def remove_stale_temporaries(path: Path) -> None:
    """Delete temporary files a killed writer of `path` left behind.

    A SIGKILL during `save_atomic` cannot clean up; the checkpoint itself is intact
    (it is only ever replaced whole), but the temporary would pile up.
    """
    path = Path(path)
    for stale in path.parent.glob(f".{path.name}.*"):
        stale.unlink(missing_ok=True)


def load_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint written by `save_atomic`, or a DataError naming the file."""
    payload = read_torch_file(path, "checkpoint")
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise DataError(f"{path} is not a relocfw checkpoint (format {CHECKPOINT_FORMAT})")
    return payload


def write_text_atomic(text: str, path: Path) -> None:
    """Results files get the same all-or-nothing treatment as checkpoints."""
    with atomic_write(path, "w") as stream:
        stream.write(text)
