"""The query fields of POST /v1/localize: the image's intrinsics and frame name.

Read by hand from the query string rather than by FastAPI's validation, so each bad
field is one line naming it ("query field fx must be finite, got 'nan'"), an unknown
field (a typo) is refused rather than ignored, and a field given twice is refused
rather than read as one of its values.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError

INTRINSICS = ("fx", "fy", "cx", "cy")
NAME = "name"
FIELDS = (*INTRINSICS, NAME)
MAX_NAME_LENGTH = 256


class FieldError(ConfigError):
    """A query field that cannot be used (answered 422)."""


@dataclass(frozen=True)
class QueryFields:
    """What the query string says: intrinsics (all four or none) and a frame name."""

    intrinsics: tuple[float, float, float, float] | None = None
    name: str | None = None

    def camera(self, width: int, height: int) -> PinholeCamera | None:
        """The pinhole camera of the decoded image; None without intrinsics."""
        if self.intrinsics is None:
            return None
        fx, fy, cx, cy = self.intrinsics
        try:
            return PinholeCamera(fx, fy, cx, cy, width, height)
        except ConfigError as error:
            raise FieldError(f"query field {error}") from error


def number(field: str, text: str) -> float:
    """A finite number from a query field's text."""
    try:
        value = float(text)
    except ValueError:
        raise FieldError(f"query field {field} must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise FieldError(f"query field {field} must be finite, got {text!r}")
    return value


def frame_name(text: str) -> str:
    """A frame name: printable, at most MAX_NAME_LENGTH characters. It only names the
    frame for a refiner that reads recordings; nothing is read from it."""
    if not text or len(text) > MAX_NAME_LENGTH or not text.isprintable():
        raise FieldError(
            f"query field name must be 1 to {MAX_NAME_LENGTH} printable characters, "
            f"got {text[:40]!r}{'...' if len(text) > 40 else ''}"
        )
    return text


def parse_fields(items: Iterable[tuple[str, str]]) -> QueryFields:
    """QueryFields of the query string's (key, value) pairs, in order.

    Raises:
        FieldError: naming the field: unknown, repeated, not a finite number, some of
            the intrinsics without the others, a name that is not printable.
    """
    given: dict[str, str] = {}
    for key, value in items:
        if key not in FIELDS:
            raise FieldError(f"unknown query field {key!r}; the fields are {', '.join(FIELDS)}")
        if key in given:
            raise FieldError(f"query field {key} is given twice")
        given[key] = value
    present = [key for key in INTRINSICS if key in given]
    if present and len(present) != len(INTRINSICS):
        missing = [key for key in INTRINSICS if key not in given]
        raise FieldError(
            f"query fields {', '.join(present)} without {', '.join(missing)}: give all of "
            "fx, fy, cx, cy (pixels of the image sent) or none"
        )
    intrinsics = None
    if present:
        fx, fy, cx, cy = (number(key, given[key]) for key in INTRINSICS)
        intrinsics = (fx, fy, cx, cy)
    name = frame_name(given[NAME]) if NAME in given else None
    return QueryFields(intrinsics, name)
