"""`relocfw task=compare`: writing the comparison table, figures and uncertainty check."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from relocfw.app.relocalize_task import write_results
from relocfw.core.json_output import strict_json
from relocfw.data.frames import Frame, mean_pose
from relocfw.model.checkpoints import write_text_atomic
from relocfw.report import figures
from relocfw.report.comparison import (
    as_csv,
    as_markdown,
    crop_seed_markdown,
    crop_seed_spread,
    median_errors,
    table_rows,
    uncertainty_check,
)
from relocfw.report.evaluation import MethodResult, constant_answer, uncertainty_quality_of
from relocfw.report.seed_comparison import SeedResults, seed_comparison, seed_footnote, seed_rows
from relocfw.report.units import (
    METRES,
    PositionUnit,
    json_note,
    relabel_table,
    relabel_tree,
    text_note,
)


@dataclass(frozen=True)
class MapView:
    """What the t-SNE figure shows: standardised map descriptors and k-means centres."""

    features: np.ndarray
    centres: np.ndarray
    labels: np.ndarray


def safe_name(scene: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in scene)


def write_comparison(
    results: Mapping[str, Mapping[str, MethodResult]],
    training_frames: Mapping[str, Sequence[Frame]],
    maps: Mapping[str, MapView | None],
    reference: str,
    run_dir: Path,
    seed: int = 0,
    seed_runs: Mapping[str, Mapping[str, Mapping[int, MethodResult]]] | None = None,
    unit: PositionUnit = METRES,
) -> dict[str, Any]:
    """Table 1 (Markdown + CSV, printed), per-scene results and the five figures.

    Args:
        seed_runs: scene -> method -> crop-search seed -> result, for the methods
            whose crop search is randomised; their spread goes to crop_seeds.md and
            comparison.json.
        unit: the positions' unit; the Markdown files start with its note, the JSON
            carries it as `units_note`, the CSV has the unit in its column titles.

    Returns:
        What comparison.json holds.
    """
    run_dir = Path(run_dir)
    header, rows = table_rows(median_errors(results), reference, unit)
    markdown = as_markdown(header, rows)
    write_text_atomic(text_note(unit) + markdown, run_dir / "comparison.md")
    write_text_atomic(as_csv(header, rows), run_dir / "comparison.csv")
    print(
        f"\nMedian position ({unit.name}) and orientation (deg) errors; "
        "average = mean over scenes\n"
    )
    print(markdown)
    summary: dict[str, Any] = {**json_note(unit), "reference": reference, "scenes": {}}
    written = []
    for scene, by_method in results.items():
        name = safe_name(scene)
        method_results = list(by_method.values())
        floor = constant_answer(
            "mean training pose", mean_pose(training_frames[scene]), method_results[0].frames
        )
        table = write_results([floor, *method_results], run_dir, name=f"_{name}", unit=unit)
        print(f"{scene}:\n{table}\n")
        title = f"({scene})"
        out = run_dir / name
        written += [
            figures.error_histogram(
                method_results,
                "position",
                Path(f"{out}_position_error_histogram.png"),
                title,
                unit,
            ),
            figures.error_histogram(
                method_results,
                "orientation",
                Path(f"{out}_orientation_error_histogram.png"),
                title,
            ),
            figures.error_curves(method_results, Path(f"{out}_error_per_image.png"), title, unit),
            figures.trajectory_top_down(
                training_frames[scene],
                method_results,
                Path(f"{out}_trajectory_top_down.png"),
                title,
                unit,
            ),
        ]
        view = maps.get(scene)
        if view is not None:
            written.append(
                figures.tsne_of_map(
                    view.features,
                    view.centres,
                    view.labels,
                    Path(f"{out}_tsne_kmeans_map.png"),
                    seed=seed,
                    title=title,
                )
            )
        checks = {m: uncertainty_check(r) for m, r in by_method.items()}
        checks = {m: c for m, c in checks.items() if c is not None}
        qualities = {m: uncertainty_quality_of(r) for m, r in by_method.items()}
        qualities = {m: q for m, q in qualities.items() if q is not None}
        for method, quality in qualities.items():
            checks[method]["quality"] = quality
            written.append(
                figures.uncertainty_against_error(
                    by_method[method],
                    quality,
                    Path(f"{out}_{safe_name(method)}_uncertainty.png"),
                    title,
                    unit,
                )
            )
            print(
                f"{method} uncertainty quality ({scene}): AUSE position "
                f"{quality['position']['ause']:.3f} {unit.name}, orientation "
                f"{quality['orientation']['ause']:.2f} deg; Spearman(spread, error) position "
                f"{quality['position']['spearman_spread_error']:.2f}, orientation "
                f"{quality['orientation']['spearman_spread_error']:.2f}"
            )
        for method, check in checks.items():
            print(
                f"{method} uncertainty ({scene}): median position error of the "
                f"{check['queries_per_group']} most uncertain queries "
                f"{check['most_uncertain_median_position_m']:.3f} {unit.name}, of the least "
                f"uncertain {check['least_uncertain_median_position_m']:.3f} {unit.name} "
                f"(rank correlation {check['spread_error_rank_correlation']:.2f})"
            )
        # Below the method names (a user's words), every key is a report key.
        summary["scenes"][scene] = {
            "uncertainty": {m: relabel_tree(c, unit) for m, c in checks.items()}
        }
    spreads = {
        scene: {method: crop_seed_spread(runs) for method, runs in by_method.items()}
        for scene, by_method in (seed_runs or {}).items()
        if by_method
    }
    if spreads:
        table = crop_seed_markdown(spreads, unit)
        write_text_atomic(text_note(unit) + table, run_dir / "crop_seeds.md")
        print("\nSpread of the medians over crop-search seeds (same model and map):\n")
        print(table)
        for scene, by_method in spreads.items():
            summary["scenes"].setdefault(scene, {})["crop_seed_spread"] = {
                method: relabel_tree(spread, unit) for method, spread in by_method.items()
            }
    summary["figures"] = [str(p) for p in written]
    write_text_atomic(strict_json(summary), run_dir / "comparison.json")
    print(f"\ncomparison: {run_dir / 'comparison.md'}; figures: {len(written)} PNG in {run_dir}")
    return summary


def seed_tables(
    table: Mapping[str, Mapping[str, Mapping[str, object]]],
    reference: str,
    seeds: Sequence[int],
    unit: PositionUnit,
) -> tuple[str, str]:
    """The seed table as Markdown (with its footnote) and as CSV, in `unit`'s terms."""
    header, rows = relabel_table(*seed_rows(table, reference), unit)
    return as_markdown(header, rows) + seed_footnote(seeds, unit.metric), as_csv(header, rows)


def write_seed_comparison(
    results: SeedResults,
    floors: Mapping[str, MethodResult],
    reference: str,
    run_dir: Path,
    bootstrap_seed: int = 0,
    unit: PositionUnit = METRES,
) -> dict[str, Any]:
    """comparison.md / .csv / .json at the top of the run: the spread over training seeds
    and each method's paired test against `reference` (printed too).

    Returns:
        What comparison.json holds (keys in `unit`'s terms).
    """
    run_dir = Path(run_dir)
    seeds = sorted(results)
    table = seed_comparison(results, floors, reference, bootstrap_seed)
    markdown, csv_text = seed_tables(table, reference, seeds, unit)
    write_text_atomic(text_note(unit) + markdown, run_dir / "comparison.md")
    write_text_atomic(csv_text, run_dir / "comparison.csv")
    scenes = {
        scene: {method: relabel_tree(stats, unit) for method, stats in by_method.items()}
        for scene, by_method in table.items()
    }
    report = {**json_note(unit), "reference": reference, "seeds": seeds, "scenes": scenes}
    write_text_atomic(strict_json(report), run_dir / "comparison.json")
    print(f"\nOver training seeds {seeds} (each seed's tables and figures: seed_<n>/)\n")
    print(markdown)
    print(f"comparison over seeds: {run_dir / 'comparison.md'}")
    return report
