"""The README's method table and the +- cells of docs/results/structure.md's
population-std tables, written from the committed results files.

Every number of the README's method table (accuracy near and far, ms per query, the
trust signals' Spearman ranges, fallbacks) is read here from a file: the families run
(benchmarks/results/families.json), the paired JSON of the run that measured a row
(benchmarks/results/*_paired.json) or, where only it holds the number, the comparison
table its compare run wrote (docs/results/**/*_comparison.md). A cell whose number no
file holds prints "-". The table sits in README.md between the markers

    <!-- table: methods (benchmarks/readme_tables.py) -->  ...  <!-- end table: methods -->

and each `+-` table of docs/results/structure.md that this script owns between

    <!-- spread cells: NAME (benchmarks/readme_tables.py) -->  ...  <!-- end spread cells -->

where the median position and orientation cells are the mean +- sample standard
deviation (ddof=1) over seeds of the per-seed medians in the named file
(docs/statistics.md#the-convention).

    .venv/bin/python benchmarks/readme_tables.py           # rewrite README.md and structure.md
    .venv/bin/python benchmarks/readme_tables.py --check   # exit 1, naming each differing row
    .venv/bin/python benchmarks/readme_tables.py --print   # the method table on stdout
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
import tempfile
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from relocfw.report.rule_study import spread_cell
from relocfw.report.statistics import spread

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path("benchmarks/results")
COMPARISONS = Path("docs/results/redkitchen")
BAYESIAN = Path("docs/results/bayesian")
README = Path("README.md")
STRUCTURE_PAGE = Path("docs/results/structure.md")

TABLE_START = "<!-- table: methods (benchmarks/readme_tables.py) -->"
TABLE_END = "<!-- end table: methods -->"
SPREAD_START = re.compile(r"<!-- spread cells: (\S+) \(benchmarks/readme_tables\.py\) -->")
SPREAD_END = "<!-- end spread cells -->"


class SourceError(Exception):
    """A results file lacks a row or a column the tables read (names file and row)."""


@dataclass(frozen=True)
class Medians:
    """One row of one run: each seed's median position (m) and orientation (deg)."""

    position_m: tuple[float, ...]
    orientation_deg: tuple[float, ...]

    def accuracy(self) -> str:
        """`position / orientation`, each the mean over seeds (the README's cells)."""
        return f"{mean(self.position_m):.3f} / {mean(self.orientation_deg):.2f}"

    def spread_cells(self) -> tuple[str, str]:
        """`mean +- sample std` over seeds, position then orientation."""
        return (
            spread_cell(spread(self.position_m), 3),
            spread_cell(spread(self.orientation_deg), 2),
        )


def mean(values: tuple[float, ...] | list[float]) -> float:
    return statistics.fmean(values)


@cache
def read_json(path: Path) -> dict:
    return json.loads((ROOT / path).read_text())


# --- the families run: benchmarks/families_table.py's JSON ---------------------------

FAMILIES = RESULTS / "families.json"


def families_row(split: str, method: str) -> dict:
    try:
        return read_json(FAMILIES)["splits"][split]["methods"][method]
    except KeyError:
        raise SourceError(f"{FAMILIES}: no row {method!r} in split {split!r}") from None


def families_medians(split: str, method: str) -> Medians:
    row = families_row(split, method)
    return Medians(
        tuple(row["median_position_m"]["values"]), tuple(row["median_orientation_deg"]["values"])
    )


def families_ms(method: str) -> float:
    """The near split's ms per query: each seed's median, averaged over seeds."""
    return mean(families_row("near", method)["ms_per_query"])


def families_fell_back(method: str) -> list[int]:
    """Fallbacks per seed over both splits (empty for a row without a refiner)."""
    counts = [families_row(split, method)["refine_fell_back"] for split in ("near", "far")]
    return [int(n) for per_seed in counts for n in per_seed if n is not None]


# --- paired runs: benchmarks/paired_runs.py's JSON -----------------------------------


def paired_side(path: Path, run_part: str, method: str) -> dict:
    """The `new` or `old` side of any pair in `path` whose run folder contains
    `run_part` (case-insensitive) and whose row is `method`. Several pairs may hold
    the same side: they must agree."""
    found = [
        pair[side]
        for pair in read_json(path).values()
        for side in ("new", "old")
        if pair[side]["method"] == method and run_part.lower() in pair[side]["run"].lower()
    ]
    if not found:
        raise SourceError(f"{path}: no row {method!r} in a run matching {run_part!r}")
    values = {(tuple(s["median_position_m"]), tuple(s["median_orientation_deg"])) for s in found}
    if len(values) > 1:
        raise SourceError(f"{path}: row {method!r} ({run_part!r}) differs between its pairs")
    return found[0]


def paired_medians(path: Path, run_part: str, method: str) -> Medians:
    side = paired_side(path, run_part, method)
    return Medians(tuple(side["median_position_m"]), tuple(side["median_orientation_deg"]))


def paired_ms(path: Path, run_part: str, method: str) -> float:
    side = paired_side(path, run_part, method)
    try:
        return mean(side["costs"]["median_ms"])
    except KeyError:
        raise SourceError(f"{path}: row {method!r} ({run_part!r}) has no costs.median_ms") from None


# --- the tables a compare run writes (comparison.md, uncertainty.md) -----------------


@cache
def markdown_rows(path: Path) -> dict[str, dict[str, str]]:
    """Row name (the `method` column) -> column header -> cell, of the first table."""
    lines = [line for line in (ROOT / path).read_text().splitlines() if line.startswith("|")]
    if len(lines) < 3:
        raise SourceError(f"{path}: no table")
    header = [cell.strip() for cell in lines[0].strip("|").split("|")]
    rows = {}
    for line in lines[2:]:
        cells = dict(
            zip(header, (cell.strip() for cell in line.strip("|").split("|")), strict=True)
        )
        rows[cells["method"]] = cells
    return rows


def markdown_cell(path: Path, method: str, column: str) -> str:
    try:
        return markdown_rows(path)[method][column]
    except KeyError:
        raise SourceError(f"{path}: no cell {column!r} in row {method!r}") from None


def markdown_mean(path: Path, method: str, column: str) -> float:
    """The mean of a `mean +- std` cell."""
    return float(markdown_cell(path, method, column).split("+-")[0])


def markdown_medians(path: Path, method: str) -> Medians:
    """A comparison table's row as one `Medians` of its means (its seeds are not kept
    apart there: only `accuracy()` is meaningful)."""
    return Medians(
        (markdown_mean(path, method, "median position (m)"),),
        (markdown_mean(path, method, "median orientation (deg)"),),
    )


def spearman_values(
    path: Path, method: str, column: str = "Spearman pos (per seed)"
) -> list[float]:
    return [float(v) for v in markdown_cell(path, method, column).split("/")]


def spearman_range(values: list[float]) -> str:
    return f"{min(values):+.2f} to {max(values):+.2f}"


def diagnose_spearman(path: Path) -> float:
    """task=diagnose's Spearman across queries (map distance against position error)."""
    found = re.search(r"Spearman across queries[^:]*:\s*([-+0-9.]+)", (ROOT / path).read_text())
    if not found:
        raise SourceError(f"{path}: no 'Spearman across queries' line")
    return float(found.group(1))


# --- the README's method table -------------------------------------------------------

REMATCH = RESULTS / "rematch_answer_test_paired.json"
SC_BOUND = RESULTS / "scene_coordinates_error_bound_test_paired.json"
REMATCH_TABLES = {
    s: COMPARISONS / f"{s}_structure_rematch_answer_comparison.md" for s in ("near", "far")
}
FAMILY_TABLES = {s: COMPARISONS / f"{s}_families_comparison.md" for s in ("near", "far")}
SC_BOUND_TABLES = {
    s: COMPARISONS / f"{s}_scene_coordinates_error_bound_comparison.md" for s in ("near", "far")
}
POSE_KEYFRAMES_TABLES = {
    "near": COMPARISONS / "near_structure_comparison.md",
    "far": COMPARISONS / "far_structure_3seeds_comparison.md",
}
BAYESIAN_TABLE = BAYESIAN / "redkitchen_near_comparison.md"
BAYESIAN_MS = BAYESIAN / "redkitchen_near_uncertainty.md"
DIAGNOSE = {s: COMPARISONS / f"{s}_diagnose.md" for s in ("near", "far")}

# Each link label of the table (its docs page is defined below the table in README.md
# and docs/index.md): what the list under the table calls it and the files read.
SOURCES = {
    "families": (
        "the families run",
        "`benchmarks/results/families.json` (`methods=families_first_choices`: near and "
        "far, 3 seeds, the 11 rows taking turns query by query, network on onnxruntime, "
        "the machine to itself); trust signals from its "
        "`docs/results/redkitchen/*_families_comparison.md`",
    ),
    "rematch-results": (
        "which solve answers",
        "`benchmarks/results/rematch_answer_test_paired.json` "
        "(`methods=structure_rematch_answer`, 3 seeds; no file keeps its ms); trust signals "
        "from its `docs/results/redkitchen/*_structure_rematch_answer_comparison.md`",
    ),
    "sc-bound": (
        "the inlier bound on the test split",
        "`benchmarks/results/scene_coordinates_error_bound_test_paired.json` "
        "(`methods=scene_coordinates_error_bound_depth`, 3 seeds, ms included); trust "
        "signals from its `docs/results/redkitchen/*_scene_coordinates_error_bound_comparison.md`",
    ),
    "structure-results": (
        "structure rows through the pipeline",
        "`docs/results/redkitchen/near_structure_comparison.md` and "
        "`far_structure_3seeds_comparison.md` (`methods=structure`, 3 seeds, on the code "
        "before the colour camera and registered depth; no file keeps its ms)",
    ),
    "bayesian": (
        "Bayesian PoseNet and uncertainty",
        "`docs/results/bayesian/redkitchen_near_comparison.md` and "
        "`redkitchen_near_uncertainty.md` (`methods=bayesian`, near, 3 seeds; * the run "
        "shared the machine)",
    ),
    "diagnose": (
        "the crop premise, diagnosed",
        "`docs/results/redkitchen/near_diagnose.md` and `far_diagnose.md` (seed 0's model)",
    ),
}

HEADER = [
    "method",
    "options",
    "near",
    "far",
    "ms / query",
    "needs depth?",
    "in a model file?",
    "trust signal",
]


def linked(text: str, label: str) -> str:
    return f"[{text}][{label}]"


def ms_cell(value: float | None, label: str, mark: str = "") -> str:
    return "-" if value is None else linked(f"{value:.1f}{mark}", label)


def spearman_over(
    tables: dict[str, Path], method: str, column: str = "Spearman pos (per seed)"
) -> str:
    return spearman_range(
        [v for path in tables.values() for v in spearman_values(path, method, column)]
    )


def fallback_range(counts: list[int]) -> str:
    if not any(counts):
        return "none of 300"
    return f"{min(counts)}-{max(counts)} of 300"


def same_answers(a: Medians, b: Medians, what: str) -> None:
    """Two files' rows answer alike per seed (to the paired files' 4 decimals), so one's
    ms measure the other's settings."""
    close = all(abs(x - y) < 6e-5 for x, y in zip(a.position_m, b.position_m, strict=True)) and all(
        abs(x - y) < 6e-4 for x, y in zip(a.orientation_deg, b.orientation_deg, strict=True)
    )
    if not close:
        raise SourceError(f"{what}: the two files' rows no longer answer alike per seed")


def families_method_row(
    label: str, options: str, method: str, depth: str, trust: str, fell_back: bool = True
) -> list[str]:
    """A row measured by the families run: accuracy, ms, trust and fallbacks from it."""
    signal = f"{trust} ({spearman_over(FAMILY_TABLES, method)})" if trust else "none measured"
    if trust and fell_back:
        signal += f", `fell_back` ({fallback_range(families_fell_back(method))})"
    return [
        label,
        f"`{options}`",
        linked(families_medians("near", method).accuracy(), "families"),
        linked(families_medians("far", method).accuracy(), "families"),
        ms_cell(families_ms(method), "families"),
        depth,
        "yes",
        signal,
    ]


def features_rows() -> list[list[str]]:
    """The structure rows at today's settings (rematch_answer_test_paired.json) and the
    depth row with one solve, whose ms the families run measured (the same answers)."""

    def rematch_row(label: str, options: str, method: str, depth: str) -> list[str]:
        trust = spearman_over(REMATCH_TABLES, method)
        return [
            label,
            f"`{options}`",
            linked(paired_medians(REMATCH, "near", method).accuracy(), "rematch-results"),
            linked(paired_medians(REMATCH, "far", method).accuracy(), "rematch-results"),
            "-",
            depth,
            "yes",
            f"PnP inliers ({trust}), `fell_back`",
        ]

    for split in ("near", "far"):
        same_answers(
            families_medians(split, "Features + depth"),
            paired_medians(REMATCH, split, "Depth"),
            f"{FAMILIES} 'Features + depth' against {REMATCH} 'Depth' ({split})",
        )
    one_solve_depth = families_method_row(
        "the same, one solve",
        "crop=centre refine=features refine.rematch=none",
        "Features + depth",
        "map images",
        "PnP inliers",
        fell_back=False,
    )
    one_solve_depth[-1] += ", `fell_back`"
    return [
        rematch_row(
            "features + PnP, keyframes by descriptor, matched again near the answer",
            "crop=centre refine=features",
            "Depth, rematch near, more inliers",
            "map images",
        ),
        one_solve_depth,
        rematch_row(
            "features + PnP, triangulated, matched again near the answer",
            "crop=centre refine=features_rgb",
            "RGB-only, rematch near, more inliers",
            "no",
        ),
        rematch_row(
            "the same, one solve",
            "crop=centre refine=features_rgb refine.rematch=none",
            "RGB-only",
            "no",
        ),
    ]


def keyframes_by_pose_row() -> list[str]:
    method = "PoseNet + features"
    return [
        "features + PnP, keyframes by pose †",
        "`crop=centre refine=features refine.keyframes=pose refine.rematch=none`",
        linked(
            markdown_medians(POSE_KEYFRAMES_TABLES["near"], method).accuracy(), "structure-results"
        ),
        linked(
            markdown_medians(POSE_KEYFRAMES_TABLES["far"], method).accuracy(), "structure-results"
        ),
        "-",
        "map images",
        "yes",
        f"PnP inliers ({spearman_over(POSE_KEYFRAMES_TABLES, method)}), `fell_back`",
    ]


def scene_coordinates_rows() -> list[list[str]]:
    method = "SC depth, 16 px"
    fell_back = [
        int(n) for s in ("near", "far") for n in paired_side(SC_BOUND, s, method)["fell_back"]
    ]
    auto = [
        "scene coordinates + PnP (auto with depth: head width 512, inlier bound 16 px)",
        "`crop=centre refine=scene_coordinates`",
        linked(paired_medians(SC_BOUND, "near", method).accuracy(), "sc-bound"),
        linked(paired_medians(SC_BOUND, "far", method).accuracy(), "sc-bound"),
        ms_cell(paired_ms(SC_BOUND, "near", method), "sc-bound"),
        "map images (`refine.depth=false`: no, head 256, the families run's RGB-only row)",
        "yes",
        f"PnP inliers ({spearman_over(SC_BOUND_TABLES, method)}), "
        f"`fell_back` ({fallback_range(fell_back)})",
    ]
    first = families_method_row(
        "the same, head width 256, 10 px (the first choices)",
        "crop=centre refine=scene_coordinates refine.head_width=256 refine.max_error_px=10",
        "Scene coordinates + depth",
        "map images",
        "PnP inliers",
    )
    return [auto, first]


def network_rows() -> list[list[str]]:
    crop_method = "Crop sampling"
    crop_sampling = [
        "crop sampling, 40 windows",
        "`crop=centre query.crop_samples=40`",
        linked(markdown_medians(BAYESIAN_TABLE, crop_method).accuracy(), "bayesian"),
        "not measured",
        ms_cell(float(markdown_cell(BAYESIAN_MS, crop_method, "med ms/query")), "bayesian", "*"),
        "no",
        "yes",
        "orientation spread "
        f"({spearman_over({'near': BAYESIAN_TABLE}, crop_method, 'Spearman ori (per seed)')})",
    ]
    map_distance = ", ".join(
        f"{diagnose_spearman(path):+.2f} {split}" for split, path in DIAGNOSE.items()
    )
    ga = families_method_row(
        "the paper's GA + k-means (default)",
        "crop=ga index=kmeans",
        "Ours (GA + k-means)",
        "no",
        "",
    )
    ga[1] = "none"
    ga[-1] = f"map distance ({linked(map_distance, 'diagnose')}, one model)"
    return [
        families_method_row("PoseNet (centre crop)", "crop=centre", "PoseNet", "no", ""),
        crop_sampling,
        families_method_row(
            "Bayesian PoseNet, 40 samples",
            "crop=centre backbone.mc_samples=40",
            "Bayesian PoseNet",
            "no",
            "position spread",
            fell_back=False,
        ),
        ga,
        families_method_row(
            "image retrieval",
            "crop=centre refine=retrieval",
            "Retrieval (keyframes)",
            "no",
            "descriptor distance",
            fell_back=False,
        ),
    ]


def method_rows() -> list[list[str]]:
    relative = families_method_row(
        "relative pose to keyframes",
        "crop=centre refine=relative",
        "Relative pose (keyframes)",
        "no",
        "inliers",
    )
    rows = features_rows()
    return [
        *rows[:2],
        keyframes_by_pose_row(),
        *rows[2:],
        relative,
        *scene_coordinates_rows(),
        *network_rows(),
    ]


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def method_table() -> str:
    """The block between the README's markers: the table, then where its numbers are."""
    sources = "".join(f"- [{name}][{label}]: {files}\n" for label, (name, files) in SOURCES.items())
    return f"{markdown_table(HEADER, method_rows())}\n\nWhere each cell's numbers are:\n\n{sources}"


# --- docs/results/structure.md: the +- cells of the tables this script owns ----------


@dataclass(frozen=True)
class SpreadRow:
    """Which row of a docs table (its leading cells, without ** markup) reads which
    file's per-seed medians."""

    key: tuple[str, ...]
    medians: Medians


def structure_spread_rows() -> dict[str, list[SpreadRow]]:
    """Per table NAME: its rows. PoseNet's seeds are the families run's: the runs share
    its cached models (their PoseNet rows answer to the digit alike)."""
    chosen = RESULTS / "structure_rgb_chosen_paired.json"
    tables: dict[str, list[SpreadRow]] = {"rgb-chosen": [], "speed": []}
    for split in ("near", "far"):
        posenet = SpreadRow((split, "PoseNet"), families_medians(split, "PoseNet"))
        tables["rgb-chosen"] += [posenet] + [
            SpreadRow((split, m), paired_medians(chosen, f"{split}_chosen", m))
            for m in ("Depth", "Depth, compact + faiss", "RGB-only, before", "RGB-only")
        ]
        speed = RESULTS / f"structure_speed_{split}_paired.json"
        tables["speed"] += [posenet] + [
            SpreadRow((split, m), paired_medians(speed, f"speed_{split}", m))
            for m in ("Depth, before", "Depth", "RGB-only, before", "RGB-only")
        ]
        geometry = RESULTS / f"structure_geometry_{split}_paired.json"
        rows = [SpreadRow(("PoseNet",), families_medians(split, "PoseNet"))]
        for method in (
            "Structure (features + depth)",
            "Structure RGB-only",
            "Relative pose (keyframes)",
        ):
            for when, run in (("before", f"{split}_base"), ("after", f"{split}_new")):
                rows.append(
                    SpreadRow((f"{method}, {when}",), paired_medians(geometry, run, method))
                )
        tables[f"geometry-{split}"] = rows
    return tables


def plain(cell: str) -> str:
    return cell.replace("**", "").strip()


def with_markup(old: str, new: str) -> str:
    """`new` in bold where `old` was."""
    return f"**{new}**" if old.startswith("**") and old.endswith("**") else new


def rewrite_spread_block(name: str, lines: list[str], rows: list[SpreadRow]) -> list[str]:
    """The block's table lines with their position and orientation cells from the files;
    a table row no SpreadRow names, or a SpreadRow no table row matches, is an error."""
    header = [plain(c) for c in lines[0].strip().strip("|").split("|")]
    position = header.index("median position (m)")
    orientation = header.index("median orientation (deg)")
    by_key = {row.key: row for row in rows}
    used = set()
    out = []
    for line in lines:
        cells = line.strip().strip("|").split("|")
        if not line.startswith("|") or set(line) <= set("|- \n") or line is lines[0]:
            out.append(line)
            continue
        width = len(next(iter(by_key)))
        key = tuple(plain(c) for c in cells[:width])
        if key not in by_key:
            raise SourceError(f"{STRUCTURE_PAGE}, table {name}: no file row for {key}")
        used.add(key)
        pos, ori = by_key[key].medians.spread_cells()
        cells[position] = f" {with_markup(cells[position].strip(), pos)} "
        cells[orientation] = f" {with_markup(cells[orientation].strip(), ori)} "
        out.append("|" + "|".join(cells) + "|" + line[len(line.rstrip("\n")) :])
    missing = set(by_key) - used
    if missing:
        raise SourceError(
            f"{STRUCTURE_PAGE}, table {name}: rows {sorted(missing)} not in the table"
        )
    return out


# --- reading and writing the marked blocks --------------------------------------------


def replace_block(text: str, start: str, end: str, block: str, path: Path) -> str:
    if text.count(start) != 1 or text.count(end) != 1:
        raise SourceError(f"{path}: expected one {start!r} and one {end!r}")
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    # Blank lines around the block: Markdown ends a table or a list only at one.
    return f"{head}{start}\n\n{block}\n{end}{tail}"


def rewritten_readme(text: str) -> str:
    return replace_block(text, TABLE_START, TABLE_END, method_table(), README)


def rewritten_structure_page(text: str) -> str:
    tables = structure_spread_rows()
    lines = text.splitlines(keepends=True)
    out: list[str] = []
    index = 0
    seen = set()
    while index < len(lines):
        found = SPREAD_START.search(lines[index])
        out.append(lines[index])
        index += 1
        if not found:
            continue
        name = found.group(1)
        if name not in tables:
            raise SourceError(f"{STRUCTURE_PAGE}: unknown spread table {name!r}")
        block = []
        while index < len(lines) and SPREAD_END not in lines[index]:
            block.append(lines[index])
            index += 1
        if index == len(lines):
            raise SourceError(f"{STRUCTURE_PAGE}: table {name} has no {SPREAD_END!r}")
        table = [line for line in block if line.startswith("|")]
        rewritten = iter(rewrite_spread_block(name, table, tables[name]))
        out += [next(rewritten) if line.startswith("|") else line for line in block]
        seen.add(name)
    if seen != set(tables):
        raise SourceError(
            f"{STRUCTURE_PAGE}: spread tables {sorted(set(tables) - seen)} not marked"
        )
    return "".join(out)


def differing_rows(current: str, wanted: str, path: Path) -> list[str]:
    """One line per table row that differs, naming the file and the row."""
    have = current.splitlines()
    want = wanted.splitlines()
    if len(have) != len(want):
        return [f"{path}: {len(have)} lines, the files give {len(want)}"]
    return [
        f"{path}: row {row_name(a)!r} differs:\n  in {path}: {a}\n  from files: {b}"
        for a, b in zip(have, want, strict=True)
        if a != b
    ]


def row_name(line: str) -> str:
    cells = [plain(c) for c in line.strip().strip("|").split("|")]
    return " | ".join(cells[:2]) if line.startswith("|") else line[:60]


PAGES = ((README, rewritten_readme), (STRUCTURE_PAGE, rewritten_structure_page))


def check(root: Path = ROOT) -> list[str]:
    """Every difference between the pages under `root` and the files (empty: agree)."""
    problems = []
    for path, rewrite in PAGES:
        text = (root / path).read_text()
        try:
            wanted = rewrite(text)
        except SourceError as error:
            problems.append(str(error))
            continue
        problems += differing_rows(text, wanted, path)
    return problems


def write(root: Path = ROOT) -> list[Path]:
    """Rewrite the marked blocks; the pages that changed."""
    changed = []
    for path, rewrite in PAGES:
        target = root / path
        text = target.read_text()
        wanted = rewrite(text)
        if wanted != text:
            handle, temporary = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.")
            with os.fdopen(handle, "w") as stream:
                stream.write(wanted)
            os.replace(temporary, target)
            changed.append(path)
    return changed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument(
        "--check", action="store_true", help="exit 1 where a page and the files differ"
    )
    mode.add_argument("--print", action="store_true", help="print the method table")
    args = parser.parse_args()
    try:
        if args.print:
            print(method_table(), end="")
        elif args.check:
            problems = check()
            for problem in problems:
                print(problem, file=sys.stderr)
            if problems:
                sys.exit(1)
            print("README.md and docs/results/structure.md agree with the results files")
        else:
            for path in write():
                print(f"rewrote {path}")
    except SourceError as error:
        sys.exit(str(error))


if __name__ == "__main__":
    main()
