"""Files written all or nothing: a temporary beside the target, renamed over it.

A run killed mid-write leaves the previous file intact, never a truncated one.
Checkpoints and model files (relocfw.model.checkpoints), results, tables and
figures are all written through here.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO


def temporary_prefix(path: Path) -> str:
    """The name every temporary of `path` starts with (hidden, beside it)."""
    return f".{Path(path).name}."


@contextmanager
def atomic_write(path: Path, mode: str = "wb") -> Iterator[IO]:
    """A stream to a temporary file beside `path`, renamed over it when the block ends.

    The data is flushed to disk before the rename; an exception (or an interrupt)
    removes the temporary and leaves `path` as it was. Text modes write newlines as
    given (no translation). The parent folder is created if needed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=temporary_prefix(path), dir=path.parent)
    try:
        with os.fdopen(handle, mode, **({} if "b" in mode else {"newline": ""})) as stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def write_text_atomic(text: str, path: Path) -> None:
    """Write `text` to `path` all or nothing (results files, tables, notes)."""
    with atomic_write(path, "w") as stream:
        stream.write(text)


def remove_stale_temporaries(path: Path) -> None:
    """Delete temporary files a killed writer of `path` left behind.

    A SIGKILL during `atomic_write` cannot clean up; `path` itself is intact (it is
    only ever replaced whole), but the temporaries would pile up. Call it only where
    no other writer of `path` can be running.
    """
    path = Path(path)
    for stale in path.parent.glob(f"{temporary_prefix(path)}*"):
        stale.unlink(missing_ok=True)
