"""The crop-headroom figures of task=diagnose (matplotlib's object API, as
relocfw.report.figures: no pyplot, no backend chosen).

Three views of the same per-offset numbers (relocfw.report.diagnosis): every window's map
distance against its pose error, the distance and error curves over the crop offset
for a few queries, and the paper's Table 3 view of a query with its centre and
min-distance crops outlined.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Rectangle

from relocfw.report.diagnosis import Picks, QueryWindows
from relocfw.report.figures import new_figure, save
from relocfw.report.units import METRES, PositionUnit

# One colour per choice, the same in every figure.
COLOURS = {"centre": "tab:blue", "min_distance": "tab:red", "oracle_position": "tab:green"}


def evenly_spaced(count: int, wanted: int) -> list[int]:
    """`wanted` query indices spread over `count` queries (all of them if fewer)."""
    if wanted <= 0 or count == 0:
        return []
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, min(wanted, count))})


def distance_vs_error(
    queries: Sequence[QueryWindows],
    picks: Sequence[Picks],
    path: Path,
    title: str = "",
    unit: PositionUnit = METRES,
) -> Path:
    """Every window's map distance against its position and orientation error.

    Centre and min-distance windows are highlighted; a non-finite pose cannot be
    drawn and is counted in the title instead.
    """
    figure, axes = new_figure((12, 4.5), 1, 2)
    for axis, kind, label in (
        (axes[0], "position_errors", f"position error ({unit.name})"),
        (axes[1], "orientation_errors", "orientation error (deg)"),
    ):
        distances = np.concatenate([q.distances for q in queries])
        errors = np.concatenate([getattr(q, kind) for q in queries])
        shown = np.isfinite(distances) & np.isfinite(errors)
        axis.scatter(distances[shown], errors[shown], s=6, color="lightgrey", label="every window")
        for name, text in (("centre", "centre crop"), ("min_distance", "min map distance")):
            rows = [getattr(k, name) for k in picks]
            x = np.array([q.distances[i] for q, i in zip(queries, rows, strict=True)])
            y = np.array([getattr(q, kind)[i] for q, i in zip(queries, rows, strict=True)])
            keep = np.isfinite(x) & np.isfinite(y)
            axis.scatter(x[keep], y[keep], s=18, color=COLOURS[name], label=text)
        hidden = int(np.sum(~shown))
        axis.set_xlabel("map distance of the window's descriptor")
        axis.set_ylabel(label)
        if hidden:
            axis.set_title(f"{hidden} windows with a non-finite pose not drawn", fontsize=8)
        axis.legend(fontsize=7)
    figure.suptitle(f"Map distance against pose error, every crop offset {title}".strip())
    return save(figure, path)


def offset_curves(
    queries: Sequence[QueryWindows],
    picks: Sequence[Picks],
    which: Sequence[int],
    path: Path,
    title: str = "",
    unit: PositionUnit = METRES,
) -> Path:
    """Distance (left axis) and position error (right axis) over the crop offset."""
    figure, axes = new_figure((8, 2.6 * len(which)), len(which), 1, squeeze=False)
    for axis, index in zip(axes[:, 0], which, strict=True):
        query, chosen = queries[index], picks[index]
        offsets = query.offsets
        axis.plot(offsets, query.distances, color="black", linewidth=1.4)
        axis.set_ylabel("map distance")
        error_axis = axis.twinx()
        error_axis.plot(offsets, query.position_errors, color="tab:purple", linewidth=1.2)
        error_axis.set_ylabel(f"position error ({unit.name})", color="tab:purple")
        for name, text in (
            ("centre", "centre"),
            ("min_distance", "min distance"),
            ("oracle_position", "oracle"),
        ):
            offset = getattr(chosen, name)
            error = query.position_errors[offset]
            axis.axvline(
                offset,
                color=COLOURS[name],
                linestyle="--",
                linewidth=1.2,
                label=f"{text} (offset {offset}, {error:.3f} {unit.name})",
            )
        axis.set_title(query.frame, fontsize=9)
        axis.legend(fontsize=7, loc="upper left")
    axes[-1, 0].set_xlabel("crop offset along the long axis (original pixels)")
    figure.suptitle(f"Distance and position error over the crop offset {title}".strip())
    figure.tight_layout()
    return save(figure, path)


def outline(axis: Axes, box: Sequence[float], colour: str, dashed: bool = False) -> None:
    x, y, side = (float(v) for v in box)
    axis.add_patch(
        Rectangle(
            (x - 0.5, y - 0.5),
            side,
            side,
            fill=False,
            edgecolor=colour,
            linewidth=1.0 if dashed else 2.0,
            linestyle="--" if dashed else "-",
        )
    )


def crops_on_images(
    queries: Sequence[QueryWindows],
    picks: Sequence[Picks],
    images: Sequence[np.ndarray],
    which: Sequence[int],
    path: Path,
    title: str = "",
    unit: PositionUnit = METRES,
) -> Path:
    """The paper's Table 3 view: a query with its centre and min-distance crops.

    Crops are outlined in original image pixels (solid); where the model's crop_scale
    shows the network only the crop's centre, that view is dashed.
    """
    figure, axes = new_figure((5 * len(which), 4.6), 1, len(which), squeeze=False)
    for axis, index in zip(axes[0], which, strict=True):
        query, chosen = queries[index], picks[index]
        axis.imshow(images[index])
        lines = []
        for name, text in (("centre", "centre"), ("min_distance", "min distance")):
            entry = getattr(chosen, name)
            outline(axis, query.crops[entry], COLOURS[name])
            if not np.allclose(query.views[entry], query.crops[entry]):
                outline(axis, query.views[entry], COLOURS[name], dashed=True)
            lines.append(
                f"{text}: {query.position_errors[entry]:.3f} {unit.name}, "
                f"{query.orientation_errors[entry]:.2f}°"
            )
        axis.set_title(f"{query.frame}\n" + "\n".join(lines), fontsize=8)
        axis.set_xticks([])
        axis.set_yticks([])
    cropped = not np.allclose(queries[which[0]].views, queries[which[0]].crops)
    seen = "; dashed: what the network sees of each" if cropped else ""
    figure.suptitle(
        f"Centre (blue) and min-distance (red) crops{seen} {title}".strip(), fontsize=10
    )
    return save(figure, path)
