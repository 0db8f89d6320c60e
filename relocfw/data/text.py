"""Line-by-line reading of pose text files, every problem named by file and line."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

from relocfw.core.errors import DataError


def data_lines(path: Path, skip: int = 0) -> Iterator[tuple[str, list[str]]]:
    """(source "file:line", fields) of each line that is not blank or a # comment.

    Args:
        path: the text file.
        skip: header lines to pass over first.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"file not found: {path}")
    try:
        text = path.read_text()
    except UnicodeDecodeError as error:
        raise DataError(f"{path}: not a text file ({error})") from error
    for number, line in enumerate(text.splitlines(), start=1):
        if number <= skip:
            continue
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.replace(",", " ").split() if "," in stripped else stripped.split()
        yield f"{path}:{number}", fields


def numbers(fields: Sequence[str], source: str, count: int) -> list[float]:
    """`count` floats from `fields`, or a DataError naming the line."""
    if len(fields) != count:
        raise DataError(f"{source}: expected {count} values, found {len(fields)}")
    try:
        values = [float(v) for v in fields]
    except ValueError as error:
        raise DataError(f"{source}: not a number ({error})") from error
    if not all(v == v and abs(v) != float("inf") for v in values):
        raise DataError(f"{source}: NaN or infinite value")
    return values
