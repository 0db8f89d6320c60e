"""Line-by-line reading of pose text files, every problem named by file and line."""

from __future__ import annotations

import csv
from collections.abc import Iterator, Sequence
from pathlib import Path

from relocfw.core.errors import DataError


def data_lines(
    path: Path, skip: int = 0, comma_fields: bool = False
) -> Iterator[tuple[str, list[str]]]:
    """(source "file:line", fields) of each line that is not blank or a # comment.

    Args:
        path: the text file.
        skip: header lines to pass over first.
        comma_fields: a line with a comma is split at commas only, as CSV (a field may
            be quoted; spaces inside a field stay), not at commas and spaces; for
            files whose fields are file names, which may hold spaces.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise DataError(f"{path}: not a text file ({error})") from error
    for number, line in enumerate(text.splitlines(), start=1):
        if number <= skip:
            continue
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        if comma_fields and "," in stripped:
            fields = csv_fields(stripped)
        elif "," in stripped:
            fields = stripped.replace(",", " ").split()
        else:
            fields = stripped.split()
        yield f"{path}:{number}", fields


def csv_fields(line: str) -> list[str]:
    """One CSV line's fields, each stripped of surrounding spaces; empty fields at
    the end (a trailing comma) are dropped, as the plain split always did."""
    fields = [field.strip() for field in next(csv.reader([line], skipinitialspace=True))]
    while fields and not fields[-1]:
        fields.pop()
    return fields


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
