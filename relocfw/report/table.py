"""The results table printed at the end of a run."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from relocfw.report.metrics import RECALL_BANDS, band_key, band_title
from relocfw.report.units import METRES, PositionUnit, relabel_key, relabel_title

COLUMNS = (
    ("median_position_m", "med pos (m)", "{:.3f}"),
    ("mean_position_m", "mean pos (m)", "{:.3f}"),
    ("median_orientation_deg", "med ori (deg)", "{:.2f}"),
    ("mean_orientation_deg", "mean ori (deg)", "{:.2f}"),
    *((band_key(m, d), band_title(m, d), "{:.1%}") for m, d in RECALL_BANDS),
    ("share_position_below_0.5m", "<0.5m", "{:.1%}"),
    ("share_orientation_below_15deg", "<15deg", "{:.1%}"),
    ("share_position_above_1m", ">1m", "{:.1%}"),
    ("share_orientation_above_20deg", ">20deg", "{:.1%}"),
    ("share_within_0.5m_15deg", "<0.5m & <15deg", "{:.1%}"),
    ("failed_queries", "failed", "{:d}"),
    ("median_seconds_per_query", "med ms/query", "{:.1f}"),
    ("mean_seconds_per_query", "mean ms/query", "{:.1f}"),
    ("mean_crops_scored", "crops/query", "{:.1f}"),
    ("mean_network_passes", "passes/query", "{:.1f}"),
)


def columns_in(unit: PositionUnit) -> list[tuple[str, str, str]]:
    """COLUMNS as `unit` names them: for a non-metric run, no metre band or share."""
    return [
        (key, relabel_title(title, unit) or title, fmt)
        for key, title, fmt in COLUMNS
        if relabel_key(key, unit) is not None
    ]


def format_table(summaries: Sequence[dict[str, Any]], unit: PositionUnit = METRES) -> str:
    """Plain-text table, one row per method; medians, means and shares over all queries
    (a failed query counts as infinitely wrong).

    Args:
        summaries: `relocfw.report.evaluation.summarise` rows (metre-named keys).
        unit: the positions' unit, for the titles and which shares mean something.
    """
    columns = columns_in(unit)
    header = ["method", *(title for _, title, _ in columns)]
    rows = []
    for summary in summaries:
        cells = [str(summary["method"])]
        for key, _, fmt in columns:
            value = summary[key]
            if key.endswith("_seconds_per_query"):
                value *= 1000.0
            cells.append(fmt.format(value))
        rows.append(cells)
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def line(cells: list[str]) -> str:
        first = cells[0].ljust(widths[0])
        rest = (c.rjust(w) for c, w in zip(cells[1:], widths[1:], strict=True))
        return "  ".join([first, *rest])

    rule = "-" * len(line(header))
    return "\n".join([line(header), rule, *(line(r) for r in rows)])
