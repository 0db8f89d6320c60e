"""The unit of a run's positions, and the one relabelling every report goes through.

The metrics are computed with metre names (`median_position_m`, `within_0.25m_2deg`,
`share_position_below_0.5m`), because most datasets are metric. A dataset whose
positions are not in metres (a COLMAP model has no scale of its own) says so with
`metric = False` and a `units_note`; its reports must then not say metres anywhere.
The writers pass their keys, column titles and figure labels through the functions
here: metre names become unit-free ones (`median_position_units`, "(model units)"),
and the metre-based recall bands and shares, meaningless at an arbitrary scale, are
left out (orientation-only shares stay).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from relocfw.report.metrics import RECALL_BANDS, band_title


@dataclass(frozen=True)
class PositionUnit:
    """How a run's positions are measured, as its reports name them.

    Attributes:
        name: what titles and labels say, in "position error (name)".
        key: the suffix of summary keys and CSV columns, as in `median_position_{key}`.
        metric: True when positions are metres, so the metre bands mean something.
        note: one line every report of a non-metric run starts with; "" when metric.
    """

    name: str
    key: str
    metric: bool
    note: str = ""

    def __post_init__(self) -> None:
        if self.metric == bool(self.note):
            raise ValueError("a metric unit has no note; a non-metric unit needs one")


METRES = PositionUnit(name="m", key="m", metric=True)
DEFAULT_NOTE = "positions are in the dataset's own units, not metres"


def model_units(note: str = DEFAULT_NOTE) -> PositionUnit:
    """The unit of a dataset without a scale of its own (e.g. a COLMAP model)."""
    return PositionUnit(name="model units", key="units", metric=False, note=note)


def unit_of(dataset: object) -> PositionUnit:
    """The unit a dataset declares: METRES unless its `metric` attribute is False.

    The one place a dataset's `metric` / `units_note` attributes are read.
    """
    if getattr(dataset, "metric", True):
        return METRES
    return model_units(str(getattr(dataset, "units_note", "") or DEFAULT_NOTE))


# A distance in metres inside a key: `within_0.05m_5deg`, `share_position_above_1m`.
METRE_DISTANCE_IN_KEY = re.compile(r"(?:^|_)\d+(?:\.\d+)?m(?=_|$)")
# The unit token of a key: `position_error_m`, `median_position_m_rejecting_10%`.
METRE_TOKEN_IN_KEY = re.compile(r"(^|_)m(?=_|$)")
# The recall bands' column titles ("25cm/2deg"), matched exactly: a title may also
# hold a method's name, which a pattern could mistake for a distance.
METRE_BAND_TITLES = frozenset(band_title(metres, degrees) for metres, degrees in RECALL_BANDS)
# The unit in a title's parentheses: "med pos (m)", "PoseNet (m, deg)".
METRE_IN_TITLE = re.compile(r"\(m([,)])")


def relabel_key(key: str, unit: PositionUnit) -> str | None:
    """A summary key or CSV column in `unit`'s terms; None for a metre band or share."""
    if unit.metric:
        return key
    if METRE_DISTANCE_IN_KEY.search(key):
        return None
    return METRE_TOKEN_IN_KEY.sub(lambda match: f"{match.group(1)}{unit.key}", key)


def relabel_title(title: str, unit: PositionUnit) -> str | None:
    """A column title in `unit`'s terms; None for a recall band's column."""
    if unit.metric:
        return title
    if title in METRE_BAND_TITLES:
        return None
    return METRE_IN_TITLE.sub(lambda match: f"({unit.name}{match.group(1)}", title)


def relabel_row(row: Mapping[str, Any], unit: PositionUnit) -> dict[str, Any]:
    """A flat summary row in `unit`'s terms: keys renamed, metre bands and shares left out."""
    relabelled = {}
    for key, value in row.items():
        new_key = relabel_key(key, unit)
        if new_key is not None:
            relabelled[new_key] = value
    return relabelled


def relabel_tree(value: Any, unit: PositionUnit) -> Any:
    """`relabel_row` at every level of nested dicts and lists.

    Only for structures whose keys are all report keys: a user's scene or method
    name used as a key (e.g. "hall_5m") must not be renamed or dropped, so callers
    apply it below those levels.
    """
    if isinstance(value, Mapping):
        return {key: relabel_tree(inner, unit) for key, inner in relabel_row(value, unit).items()}
    if isinstance(value, list):
        return [relabel_tree(inner, unit) for inner in value]
    return value


def relabel_table(
    header: Sequence[str], rows: Sequence[Sequence[str]], unit: PositionUnit
) -> tuple[list[str], list[list[str]]]:
    """A (header, rows) table in `unit`'s terms: metre-band columns left out, "(m)" renamed."""
    titles = [relabel_title(title, unit) for title in header]
    kept = [i for i, title in enumerate(titles) if title is not None]
    return [titles[i] for i in kept], [[row[i] for i in kept] for row in rows]


def text_note(unit: PositionUnit) -> str:
    """The first lines of a text or Markdown report: the note and a blank line, or ""."""
    return f"Note: {unit.note}.\n\n" if unit.note else ""


def json_note(unit: PositionUnit) -> dict[str, str]:
    """The field a JSON report carries first: {"units_note": note}, or {} when metric."""
    return {"units_note": unit.note} if unit.note else {}
