"""Checkpoint files: named by what produced them, written atomically
(relocfw.core.atomic_files)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import torch

# The generic writers live in core; still importable from here, their first path.
from relocfw.core.atomic_files import (  # noqa: F401
    atomic_write,
    remove_stale_temporaries,
    write_text_atomic,
)
from relocfw.core.errors import DataError

# Bump when the layout of saved models changes: it is part of every checkpoint's key,
# so an old checkpoint is never picked up by code that cannot read it.
CHECKPOINT_FORMAT = 3


def settings_key(settings: dict[str, Any]) -> str:
    """Short stable hash of everything that determines a trained model."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


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


def load_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint written by `save_atomic`, or a DataError naming the file."""
    payload = read_torch_file(path, "checkpoint")
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise DataError(f"{path} is not a relocfw checkpoint (format {CHECKPOINT_FORMAT})")
    return payload
