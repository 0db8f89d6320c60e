"""The families table (docs/results/families.md): the rows of
`relocfw task=compare methods=families` (3 training seeds, round robin, paired
against PoseNet), grouped by the paper's three families, beside what each row costs
to build and ship (benchmarks/family_costs.py).

Reads each split's compare run folder (comparison.json: the spread over seeds and
the paired tests; seed_<n>/summary_<scene>.json: fallbacks and ms per query) and the
costs JSON, and writes one Markdown table per split and a JSON of the same numbers.
An optional unpaired row (COLMAP's points, which need dataset=colmap and so run on
their own queries) is read from benchmarks/results/colmap_points.json and marked so.

    .venv/bin/python benchmarks/families_table.py --split near=outputs/families_near \\
        --split far=outputs/families_far --costs benchmarks/results/family_costs.json \\
        --out benchmarks/results/families.json --markdown docs/results/families_tables.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml
from common import write_json  # benchmarks/, the script's own folder

from relocfw.app.split_record import SEVENSCENES_POSE_FILES, sha256_of, split_line
from relocfw.data.sevenscenes import SPLIT_FILES, read_split, scene_folder
from relocfw.model.checkpoints import write_text_atomic
from relocfw.report.comparison import as_markdown
from relocfw.report.rule_study import spread_cell
from relocfw.report.seed_comparison import paired_cell

# The methods file whose rows the table reads; each row's family follows from its
# overrides (family_of), so the row names live in that file only.
METHODS_FILE = Path(__file__).resolve().parents[1] / "conf" / "methods" / "families.yaml"
# The paper's division of relocalizers, by the refiner a row runs: keyframe-based
# (retrieve keyframes, transfer or relate their poses), feature-based (local features
# against a 3-D map); every other row regresses its pose or scene coordinates with a
# learned network.
KEYFRAME_REFINERS = ("retrieval", "relative")
FEATURE_REFINERS = ("features", "features_rgb", "features_colmap")


def family_of(overrides: list[str]) -> str:
    """keyframe, feature or learning: the family of a methods-file row's overrides."""
    refiner = next((o.split("=", 1)[1] for o in overrides if o.startswith("refine=")), None)
    if refiner in KEYFRAME_REFINERS:
        return "keyframe"
    if refiner in FEATURE_REFINERS:
        return "feature"
    return "learning"


def families(methods_file: Path = METHODS_FILE) -> dict[str, str]:
    """Row name -> family, for every row of the methods file (a row not in it is
    "other" in the table)."""
    rows = yaml.safe_load(methods_file.read_text())
    if not isinstance(rows, dict):
        sys.exit(f"{methods_file}: a mapping of row name to overrides expected")
    return {str(name): family_of([str(o) for o in overrides]) for name, overrides in rows.items()}


FAMILY = families()
ORDER = ("keyframe", "feature", "learning", "other")
HEADER = [
    "family",
    "method",
    "median position (m)",
    "median orientation (deg)",
    "5 cm / 5 deg",
    "fell back (per seed)",
    "position vs PoseNet (m)",
    "orientation vs PoseNet (deg)",
    "network training (s)",
    "map / head fit (s)",
    "model file (MB)",
    "median ms per query (mean of seeds)",
]


def seed_summaries(run: Path, scene: str, seeds: list[int]) -> list[dict[str, dict]]:
    """Per seed: method -> its summary row (fallbacks, ms per query)."""
    found = []
    for seed in seeds:
        path = run / f"seed_{seed}" / f"summary_{scene}.json"
        if not path.is_file():
            sys.exit(f"{path}: missing; is {run} a finished multi-seed compare run?")
        found.append({row["method"]: row for row in json.loads(path.read_text())})
    return found


def cost_cells(costs: dict | None, method: str) -> tuple[list[str], dict]:
    """Network training, fit and model-file cells of one row, and their JSON."""
    row = (costs or {}).get("rows", {}).get(method)
    if row is None:
        return ["-", "-", "-"], {}
    shared = row["network_trained_by"] != method
    owner = row["network_trained_by"]
    network = (
        f"({owner}'s: {costs['rows'][owner]['network_seconds']:.0f})"
        if shared
        else f"{row['network_seconds']:.0f}"
    )
    fit = f"{row['fit_seconds']:.0f}"
    parts = row.get("fit_parts_seconds")
    if parts and "training" in parts:
        fit += f" (head {parts['training']:.0f})"
    size = f"{row['model_bytes'] / 1e6:.1f}"
    if not row["refiner_stored"]:
        size += " (no refiner)"
    return [network, fit, size], row


def split_table(name: str, run: Path, costs: dict | None) -> tuple[str, dict]:
    comparison = json.loads((run / "comparison.json").read_text())
    if "seeds" not in comparison:
        sys.exit(f"{run}: a compare run over several seeds (compare.seeds) expected")
    if comparison["reference"] != "PoseNet":
        sys.exit(f"{run}: rows paired against {comparison['reference']!r}, not PoseNet")
    seeds = comparison["seeds"]
    (scene, methods), *more = comparison["scenes"].items()
    if more:
        sys.exit(f"{run}: one scene per run expected, found {len(more) + 1}")
    summaries = seed_summaries(run, scene, seeds)
    rows, report = [], {}
    ranked = sorted(
        (m for m in methods if m != "mean training pose"),
        key=lambda m: ORDER.index(FAMILY.get(m, "other")),
    )
    for method in ranked:
        stats = methods[method]
        per_seed = [s[method] for s in summaries]
        # A row without a refiner has nothing to fall back from: "-", not "0".
        fell_back = [s.get("refine_fell_back") for s in per_seed]
        ms = [1000 * s["median_seconds_per_query"] for s in per_seed]
        paired = stats.get("vs_reference")
        cells, cost = cost_cells(costs, method)
        rows.append(
            [
                FAMILY.get(method, "other"),
                method,
                spread_cell(stats["median_position_m"], 3),
                spread_cell(stats["median_orientation_deg"], 2),
                f"{100 * stats['within_0.05m_5deg']['mean']:.1f}%",
                " ".join("-" if n is None else str(int(n)) for n in fell_back),
                paired_cell(paired["position_m"], ".3f") if paired else "(reference)",
                paired_cell(paired["orientation_deg"], ".2f") if paired else "(reference)",
                *cells,
                f"{sum(ms) / len(ms):.1f}",
            ]
        )
        report[method] = {
            "family": FAMILY.get(method, "other"),
            "median_position_m": stats["median_position_m"],
            "median_orientation_deg": stats["median_orientation_deg"],
            "within_0.05m_5deg": stats["within_0.05m_5deg"],
            "refine_fell_back": fell_back,
            "ms_per_query": ms,
            "vs_posenet": paired,
            "costs": cost,
        }
    split = run_split(run, comparison, scene)
    markdown = f"### {name}\n\n{split_line(split)}\n\n" + as_markdown(HEADER, rows)
    return markdown, {
        "run": str(run),
        "seeds": seeds,
        "scene": scene,
        "split": split,
        "methods": report,
    }


def run_split(run: Path, comparison: dict, scene: str) -> dict:
    """The run's split record (relocfw.app.split_record): comparison.json's `splits`
    where the run wrote one, else made from the options it ran with
    (.hydra/config.yaml: dataset.train_sequences, test_sequences, poses_of and pgt;
    a run of a families table is a test run, so no validation queries)."""
    recorded = comparison.get("splits", {}).get(scene)
    if recorded is not None:
        return recorded
    config = run / ".hydra" / "config.yaml"
    if not config.is_file():
        sys.exit(f"{run}: neither comparison.json's splits nor {config} says its sequences")
    dataset = yaml.safe_load(config.read_text())["dataset"]
    folder = scene_folder(dataset["root"], dataset.get("scene"))
    record = {"validation": None}
    for split in ("train", "test"):
        chosen = dataset.get(f"{split}_sequences")
        record[f"{split}_sequences"] = chosen or read_split(folder / SPLIT_FILES[split])
        record[f"{split}_source"] = (
            f"dataset.{split}_sequences" if chosen else str(folder / SPLIT_FILES[split])
        )
    pgt = dataset.get("pgt")
    if pgt:
        reference = {"kind": "pgt", "file": pgt, "sha256": sha256_of(Path(pgt))}
    else:
        reference = {
            "kind": "dataset poses",
            "file": str(folder / SEVENSCENES_POSE_FILES),
            "sha256": None,
            "poses_of": dataset.get("poses_of", "colour"),
        }
    return record | {"pose_reference": reference}


def colmap_rows(path: Path) -> str:
    """The COLMAP rows: their own queries and one model, so no spread and no pair."""
    found = json.loads(path.read_text())
    lines = [
        f"From `{found['command']}`: a pycolmap model of {found['map_images']} map images, "
        f"{found['query_images']} queries of its own (unpaired with the tables above)."
    ]
    for name, row in found["rows"].items():
        # Rows name the overrides that composed them; older files only the refine=.
        composed = " ".join(row.get("overrides", [f"refine={name}"]))
        lines.append(
            f"- `{composed}` ({row['structure_source']} points): "
            f"{row['median_position_m']:.3f} m / {row['median_orientation_deg']:.2f} deg, "
            f"{100 * row['within_5cm_5deg']:.0f}% within 5 cm / 5 deg, "
            f"{row['fallbacks']} of {row['queries']} fell back, map built in "
            f"{row['map_build_s']:.0f} s, {1000 * row['median_query_s']:.0f} ms per query"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--split", action="append", required=True, help="NAME=compare run folder (repeatable)"
    )
    parser.add_argument("--costs", type=Path, help="benchmarks/family_costs.py's JSON")
    parser.add_argument("--colmap", type=Path, help="benchmarks/colmap_points.py's JSON")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/families.json"))
    parser.add_argument("--markdown", type=Path, help="also write the tables to this file")
    args = parser.parse_args()
    costs = json.loads(args.costs.read_text()) if args.costs else None
    parts, report = [], {"costs": costs, "splits": {}}
    for split in args.split:
        name, _, folder = split.partition("=")
        if not folder:
            sys.exit(f"--split {split!r}: give NAME=FOLDER, e.g. near=outputs/families_near")
        markdown, report["splits"][name] = split_table(name, Path(folder), costs)
        parts.append(markdown)
    if args.colmap:
        parts.append(
            "### COLMAP's points (dataset=colmap, unpaired)\n\n" + colmap_rows(args.colmap)
        )
    text = "\n".join(parts)
    print(text)
    write_json(report, args.out)
    if args.markdown:
        write_text_atomic(text + "\n", args.markdown)


if __name__ == "__main__":
    main()
