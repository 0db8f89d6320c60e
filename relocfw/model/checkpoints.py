"""Checkpoint files: named by what produced them, written atomically
(relocfw.core.atomic_files)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import torch
from packaging.version import InvalidVersion, Version

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
# The first torch whose weights-only loader is safe on a file from anyone: below 2.6 a
# crafted file runs code (CVE-2025-32434), and up to 2.9.1 it can corrupt memory
# (GHSA-63cw-57p8-fm3p, fixed in 2.10.0). pyproject.toml asks for it, but a user can
# pin any torch, so no file is read under an older one (read_torch_file).
SAFE_TORCH = Version("2.10.0")


def settings_key(settings: dict[str, Any]) -> str:
    """Short stable hash of everything that determines a trained model."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def save_atomic(payload: dict[str, Any], path: Path) -> None:
    """torch.save `payload` to `path` atomically."""
    with atomic_write(path, "wb") as stream:
        torch.save(payload, stream)


def installed_torch() -> str:
    """The installed torch's version, e.g. "2.13.0+cpu"."""
    return str(torch.__version__)


def is_safe_torch(version: str) -> bool:
    """True when torch `version` is SAFE_TORCH or later.

    A pre-release or development build of a release ("2.10.0rc1", "2.10.0a0+git...")
    counts as before it (the fix may not be in it), a local build of it ("+cpu") as
    it. A version that cannot be read is not trusted.
    """
    try:
        return Version(version.strip()) >= SAFE_TORCH
    except InvalidVersion:
        return False


def refuse_unsafe_torch(path: Path, what: str) -> None:
    """A DataError naming `path` when the installed torch's loader is unsafe."""
    installed = installed_torch()
    if not is_safe_torch(installed):
        floor = str(SAFE_TORCH)
        raise DataError(
            f"{what}: refused to read {path} with torch {installed}: its weights-only "
            f"loader is unsafe on a crafted file before torch {floor} (CVE-2025-32434, "
            f"GHSA-63cw-57p8-fm3p); install torch>={floor}"
        )


def read_torch_file(path: Path, what: str) -> Any:
    """Tensors saved with torch.save, loaded safely (no pickled code) onto the CPU.

    Every torch file relocfw reads (model files, checkpoints, pretrained weights)
    comes through here, so none is read under a torch older than SAFE_TORCH.

    Args:
        path: the file.
        what: how to name it in an error, e.g. "checkpoint" or "backbone.weights".

    Raises:
        DataError: the file is missing or unreadable, or the installed torch is older
            than SAFE_TORCH (then nothing is read).
    """
    path = Path(path)
    refuse_unsafe_torch(path, what)
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
