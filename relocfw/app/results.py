"""One method's run on a test split and its result files (task=relocalize, compare)."""

from __future__ import annotations

import csv
import io
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from relocfw.core.json_output import strict_json
from relocfw.core.pipeline import Relocalizer
from relocfw.data.frames import Frame
from relocfw.model.checkpoints import write_text_atomic
from relocfw.report.calibration import Calibration, calibrate_relocalizer
from relocfw.report.evaluation import MethodResult, evaluate, per_image_csv, summarise
from relocfw.report.table import format_table
from relocfw.report.units import METRES, PositionUnit, json_note, relabel_row, text_note

Split = tuple[Sequence[Frame], Sequence[np.ndarray]]


def safe_name(name: str) -> str:
    """A scene's or method's name as a file name: letters, digits, - and _ only."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def run_method(
    method: str,
    relocalizer: Relocalizer,
    train: Split,
    test: Split,
    quiet: bool = False,
    calibration: Calibration | None = None,
) -> tuple[MethodResult, np.ndarray]:
    """Fit the map on the training split, calibrate the error bounds on the
    validation block where there is one, and relocalize the test split.

    Returns:
        The method's answers and the map's [N, D] training descriptors.
    """
    features = fit_method(method, relocalizer, train, quiet, calibration)
    return evaluate(method, relocalizer, *test, quiet=quiet), features


def fit_method(
    method: str,
    relocalizer: Relocalizer,
    train: Split,
    quiet: bool = False,
    calibration: Calibration | None = None,
) -> np.ndarray:
    """Fit the map on the training split and calibrate the error bounds on the
    validation block where there is one; the map's [N, D] training descriptors."""
    frames = train[0]
    features = relocalizer.fit(
        train[1],
        [f.pose for f in frames],
        quiet=quiet,
        frames=frames,
    )
    note_skipped_views(method, relocalizer)
    if calibration is not None:
        bounds, _ = calibrate_relocalizer(relocalizer, calibration, quiet)
        print(f"{method}: {bounds.describe()}")
    return features


def note_skipped_views(method: str, relocalizer: Relocalizer) -> None:
    """Say which map images the refiner could not use (e.g. no depth): never silent."""
    skipped = tuple(getattr(relocalizer.refiner, "skipped_views", ()))
    if skipped:
        first = skipped[0]
        print(
            f"note: {method}: {len(skipped)} of {len(relocalizer.map_poses)} map images give "
            f"the refiner no 3-D point (first: {first.name}: {first.reason})",
            file=sys.stderr,
        )


def summary_csv(summaries: Sequence[dict[str, Any]]) -> str:
    """One row per method, one column per summary key (metrics, shares and costs)."""
    stream = io.StringIO()
    # Sampled methods carry extra uncertainty columns: the union, in first-seen order.
    fields = list(dict.fromkeys(key for summary in summaries for key in summary))
    writer = csv.DictWriter(stream, fieldnames=fields, restval="")
    writer.writeheader()
    writer.writerows(summaries)
    return stream.getvalue()


def write_results(
    results: Sequence[MethodResult],
    run_dir: Path,
    name: str = "",
    unit: PositionUnit = METRES,
    split: dict[str, Any] | None = None,
) -> str:
    """results{name}.csv (per query), summary{name}.json and .csv (per method) and
    table{name}.txt; returns the table.

    With `split` (relocfw.app.split_record), every row of summary{name}.json carries
    it as `split`: the sequences and the poses the numbers come from.

    Each file names the positions' unit as it is written: table{name}.txt starts with
    the unit's note, every summary row (JSON and CSV) carries it as `units_note`, and
    results{name}.csv has the unit in its column names. Files from earlier runs in
    `run_dir` are replaced, never annotated.
    """
    summaries = [summarise(r) for r in results]
    rows = [relabel_row(summary, unit) | json_note(unit) for summary in summaries]
    run_dir = Path(run_dir)
    write_text_atomic(per_image_csv(results, unit), run_dir / f"results{name}.csv")
    recorded = rows if split is None else [row | {"split": split} for row in rows]
    write_text_atomic(strict_json(recorded), run_dir / f"summary{name}.json")
    write_text_atomic(summary_csv(rows), run_dir / f"summary{name}.csv")
    table = format_table(summaries, unit)
    write_text_atomic(text_note(unit) + table + "\n", run_dir / f"table{name}.txt")
    return table
