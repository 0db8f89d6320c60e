"""task=diagnose: does the crop nearest the map give a better pose than the centre crop?

The same model and map as task=relocalize (the checkpoint is trained or reused by the
same key, the map fitted with the configured index); then every crop offset of every
test query is scored (relocfw.report.diagnosis) and the numbers, table, windows and
figures written to the run directory.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from relocfw.app.engines import on_engine
from relocfw.app.methods import dataset_settings, scene_name
from relocfw.app.split_record import split_line, split_record
from relocfw.app.splits import load_split, write_skipped
from relocfw.app.tasks.train import trained
from relocfw.core.json_output import strict_json
from relocfw.core.options import integer_at_least
from relocfw.core.version import VERSION
from relocfw.model.checkpoints import write_text_atomic
from relocfw.model.distributed import World
from relocfw.report import diagnose_figures
from relocfw.report.diagnosis import Picks, QueryWindows, diagnose, picks_of, summarise_queries
from relocfw.report.units import (
    METRES,
    PositionUnit,
    json_note,
    relabel_key,
    relabel_tree,
    text_note,
    unit_of,
)
from relocfw.report.window_recording import save_windows

CHOICE_NAMES = {
    "centre": "centre crop",
    "min_distance": "min map distance",
    "oracle_position": "oracle (position)",
    "oracle_orientation": "oracle (orientation)",
}
WINDOW_COLUMNS = (
    "frame",
    "offset",
    "crop_x",
    "crop_y",
    "crop_size",
    "distance",
    "position_error_m",
    "orientation_error_deg",
    "is_centre",
    "is_min_distance",
    "is_oracle",
    "is_oracle_orientation",
)


def number(value: float, digits: int) -> str:
    return "n/a" if math.isnan(value) else f"{value:.{digits}f}"


def p_value(value: float) -> str:
    """Two significant digits: a small p reads 3.2e-06, never 0.000."""
    return "n/a" if math.isnan(value) else f"{value:.2g}"


def as_markdown(scene: str, summary: dict[str, Any], unit: PositionUnit = METRES) -> str:
    """The scene's table: each crop choice's errors (`summarise_queries`' metre-named
    keys; titles in `unit`), then the premise's tests."""
    pos = unit.name
    lines = [
        f"## {scene}: {summary['queries']} queries, "
        f"{summary['mean_offsets_per_query']:.1f} crop offsets "
        f"({summary['mean_windows_per_query']:.1f} distinct windows) per query",
        "",
        f"| crop choice | median pos ({pos}) | mean pos ({pos}) | median ori (deg) "
        "| mean ori (deg) |",
        "|---|---|---|---|---|",
    ]
    for key, name in CHOICE_NAMES.items():
        e = summary["errors"][key]
        lines.append(
            f"| {name} | {e['median_position_m']:.3f} | {e['mean_position_m']:.3f} | "
            f"{e['median_orientation_deg']:.2f} | {e['mean_orientation_deg']:.2f} |"
        )
    versus = summary["min_distance_vs_centre"]
    within = summary["spearman_within"]
    lines += [
        "",
        f"- min map distance vs centre crop (position): better on "
        f"{versus['share_better_position']:.0%} of queries, worse on "
        f"{versus['share_worse_position']:.0%}; paired Wilcoxon signed-rank p = "
        f"{p_value(versus['wilcoxon_p_position'])} ({versus['wilcoxon_pairs']} untied pairs)",
        f"- Spearman(map distance, position error) within a query: median "
        f"{number(within['median'], 2)}, positive in {number(100 * within['share_positive'], 0)}% "
        f"of {within['queries']} queries",
        f"- Spearman across queries (each query's min distance vs its window's position "
        f"error): {number(summary['spearman_across'], 2)}",
    ]
    return "\n".join(lines) + "\n"


def windows_csv(
    queries: Sequence[QueryWindows], picks: Sequence[Picks], unit: PositionUnit = METRES
) -> str:
    """One row per query and crop offset, with which rules chose it; the positions'
    unit is in the column names, so the file needs no note."""
    stream = io.StringIO()
    writer = csv.writer(stream)
    writer.writerow([relabel_key(column, unit) for column in WINDOW_COLUMNS])
    for query, chosen in zip(queries, picks, strict=True):
        for i in query.offsets:
            x, y, size = query.crops[i]
            writer.writerow(
                [
                    query.frame,
                    int(i),
                    int(x),
                    int(y),
                    int(size),
                    f"{query.distances[i]:.6f}",
                    f"{query.position_errors[i]:.6f}",
                    f"{query.orientation_errors[i]:.4f}",
                    int(i == chosen.centre),
                    int(i == chosen.min_distance),
                    int(i == chosen.oracle_position),
                    int(i == chosen.oracle_orientation),
                ]
            )
    return stream.getvalue()


def write_diagnosis(
    scene: str,
    queries: Sequence[QueryWindows],
    images: Sequence[np.ndarray],
    run_dir: Path,
    settings: dict[str, Any],
    curve_queries: int = 4,
    table3_queries: int = 3,
    unit: PositionUnit = METRES,
    split: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """diagnose.json, diagnose.md (printed), diagnose_windows.csv and the figures.

    Args:
        scene: the dataset's name, the table's heading.
        queries: what `relocfw.report.diagnosis.diagnose` returned.
        images: the query images, aligned with `queries` (for the Table 3 view).
        settings: how the numbers were made (method, model, dataset); saved as is.
        curve_queries: queries whose curves over the offset are drawn (0: no figure).
        table3_queries: queries drawn with their crops outlined (0: no figure).
        unit: the positions' unit: diagnose.md starts with its note, diagnose.json
            carries it as `units_note`, the CSV and figures name it.
        split: the run's split record (relocfw.app.split_record): diagnose.json
            carries it as `split`, diagnose.md says it in one line.

    Returns:
        What diagnose.json holds.
    """
    run_dir = Path(run_dir)
    picks = picks_of(queries)
    summary = summarise_queries(queries)
    summary["mean_windows_per_query"] = float(np.mean([q.windows for q in queries]))
    markdown = as_markdown(scene, summary, unit)
    if split is not None:
        markdown = split_line(split) + "\n\n" + markdown
    write_text_atomic(text_note(unit) + markdown, run_dir / "diagnose.md")
    write_text_atomic(windows_csv(queries, picks, unit), run_dir / "diagnose_windows.csv")
    title = f"({scene})"
    written = [
        diagnose_figures.distance_vs_error(
            queries, picks, run_dir / "diagnose_distance_vs_error.png", title, unit
        )
    ]
    curves = diagnose_figures.evenly_spaced(len(queries), curve_queries)
    if curves:
        written.append(
            diagnose_figures.offset_curves(
                queries, picks, curves, run_dir / "diagnose_offset_curves.png", title, unit
            )
        )
    shown = diagnose_figures.evenly_spaced(len(queries), table3_queries)
    if shown:
        written.append(
            diagnose_figures.crops_on_images(
                queries, picks, images, shown, run_dir / "diagnose_crops.png", title, unit
            )
        )
    report = {
        **json_note(unit),
        "settings": settings,
        **({"split": split} if split is not None else {}),
        # The scene's name is the user's; below it every key is a report key.
        "scenes": {scene: relabel_tree(summary, unit)},
        "figures": [str(p) for p in written],
    }
    write_text_atomic(strict_json(report), run_dir / "diagnose.json")
    print("\n" + markdown)
    print(
        f"diagnosis: {run_dir / 'diagnose.md'}, {run_dir / 'diagnose.json'}, "
        f"{run_dir / 'diagnose_windows.csv'}, {run_dir / 'diagnose_windows.npz'}; "
        f"figures: {len(written)} PNG in {run_dir}"
    )
    if unit.note:
        print(f"note: {unit.note}")
    return report


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    """Train or reuse the model, fit the map, score every crop offset, write the files."""
    # Checked before any slow work (the schema has already checked they are integers).
    curve_queries = integer_at_least("diagnose.curve_queries", cfg.diagnose.curve_queries, 0)
    table3_queries = integer_at_least("diagnose.table3_queries", cfg.diagnose.table3_queries, 0)
    done = trained(cfg, device, world, map_size=True)
    choices = HydraConfig.get().runtime.choices
    quiet = bool(cfg.quiet)
    test = load_split(done.dataset, "test", quiet)
    write_skipped(done.dataset, done.run_dir)
    method = done.method
    relocalizer = on_engine(cfg, method.relocalizer(device), done.checkpoint, device, done.train[1])
    # The refiner is not applied per window (the note below), so it is not fitted either:
    # fitting one can take minutes (refine=sequence trains a network, refine=features
    # builds a 3-D map).
    relocalizer.refiner = None
    map_poses = [f.pose for f in done.train[0]]
    map_features = relocalizer.fit(done.train[1], map_poses, quiet=quiet)
    refine = choices.get("refine", "none")
    if refine != "none":
        print(
            f"note: task=diagnose scores every window by the network's pose; refine={refine} "
            "answers for a chosen crop only and is not applied per window"
        )
    queries = diagnose(relocalizer, *test, quiet=quiet, map_features=map_features)
    save_windows(done.run_dir / "diagnose_windows.npz", queries, map_poses)
    settings = {
        "crops": "every offset at stride 1 (the configured crop search is not used)",
        "backbone": choices["backbone"],
        "backbone_options": method.part_options["backbone"],
        "index": choices["index"],
        "index_options": method.part_options["index"],
        # Every window's pose is the network's (Relocalizer.pose_of): a refiner, e.g.
        # refine=retrieval, answers for the chosen crop only and is not applied here.
        "refine": choices.get("refine", "none"),
        "poses": "the network's pose of each window (refine= is not applied per window)",
        "scoring": "plain (every window through the whole network)",
        "input_size": int(relocalizer.backbone.input_size),
        "crop_scale": relocalizer.crop_scale,
        "query_batch_size": method.query.batch_size,
        "dataset": choices["dataset"],
        "scene": scene_name(cfg, choices),
        "dataset_settings": dataset_settings(cfg),
        "map_images": len(done.train[0]),
        "test_queries": len(test[0]),
        "checkpoint": str(done.checkpoint),
        "curve_queries": curve_queries,
        "table3_queries": table3_queries,
        "relocfw_version": VERSION,
    }
    write_diagnosis(
        scene_name(cfg, choices),
        queries,
        test[1],
        done.run_dir,
        settings,
        curve_queries,
        table3_queries,
        unit=unit_of(done.dataset),
        split=split_record(done.dataset, done.train[0], test[0], done.calibration),
    )
