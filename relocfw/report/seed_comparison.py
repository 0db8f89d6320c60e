"""task=compare over several training seeds: each method's spread, and paired tests."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from relocfw.report.comparison import as_markdown
from relocfw.report.evaluation import MethodResult
from relocfw.report.metrics import RECALL_BANDS, accuracy_metrics, band_key, band_title
from relocfw.report.statistics import paired_test, spread

# Seed -> scene -> method -> result.
SeedResults = Mapping[int, Mapping[str, Mapping[str, MethodResult]]]


def stacked_errors(
    by_seed: Mapping[int, MethodResult], seeds: Sequence[int]
) -> tuple[np.ndarray, np.ndarray]:
    """[S, N] position and orientation errors, one row per seed, queries aligned."""
    names = [f.name for f in by_seed[seeds[0]].frames]
    for seed in seeds:
        if [f.name for f in by_seed[seed].frames] != names:
            raise ValueError(f"seed {seed} answered other queries than seed {seeds[0]}")
    positions = np.stack([by_seed[s].position_errors() for s in seeds])
    orientations = np.stack([by_seed[s].orientation_errors() for s in seeds])
    return positions, orientations


def method_statistics(
    positions: np.ndarray,
    orientations: np.ndarray,
    reference: tuple[np.ndarray, np.ndarray] | None,
    bootstrap_seed: int,
) -> dict[str, object]:
    """One method's per-seed metrics, their spread, and its paired test (if any)."""
    per_seed = [accuracy_metrics(p, o) for p, o in zip(positions, orientations, strict=True)]
    keys = [k for k in per_seed[0] if k != "failed_queries"]
    statistics: dict[str, object] = {key: spread([m[key] for m in per_seed]) for key in keys}
    statistics["failed_queries"] = [m["failed_queries"] for m in per_seed]
    if reference is not None:
        statistics["vs_reference"] = {
            "position_m": paired_test(positions, reference[0], seed=bootstrap_seed),
            "orientation_deg": paired_test(orientations, reference[1], seed=bootstrap_seed),
        }
    return statistics


def seed_comparison(
    results: SeedResults,
    floors: Mapping[str, MethodResult],
    reference: str,
    bootstrap_seed: int = 0,
) -> dict[str, dict[str, dict[str, object]]]:
    """scene -> method -> statistics over training seeds (see `method_statistics`).

    Args:
        results: seed -> scene -> method -> result; every seed has the same scenes,
            methods and queries.
        floors: scene -> the mean-training-pose answers, a row that needs no seeds
            (training frames are the same for every seed).
        reference: the method every other method (and the floor) is tested against.
    """
    seeds = sorted(results)
    first = results[seeds[0]]
    table: dict[str, dict[str, dict[str, object]]] = {}
    for scene, by_method in first.items():
        if reference not in by_method:
            raise KeyError(f"compare.reference {reference!r} is not one of {list(by_method)}")
        errors: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        floor = floors.get(scene)
        if floor is not None:
            rows = (len(seeds), 1)
            errors[floor.method] = (
                np.tile(floor.position_errors(), rows),
                np.tile(floor.orientation_errors(), rows),
            )
        for method in by_method:
            errors[method] = stacked_errors({s: results[s][scene][method] for s in seeds}, seeds)
        ref = errors[reference]
        table[scene] = {
            method: method_statistics(p, o, None if method == reference else ref, bootstrap_seed)
            for method, (p, o) in errors.items()
        }
    return table


def paired_cell(test: Mapping[str, object], unit_format: str) -> str:
    """One paired test as `difference [low, high], p=...: verdict`."""
    low, high = test["bootstrap_95"]
    difference = test["median_difference"]
    # NaN: failures on opposite seeds leave no difference to print (see paired_test).
    shown = "undefined" if np.isnan(difference) else f"{difference:+{unit_format}}"
    return (
        f"{shown} [{low:+{unit_format}}, {high:+{unit_format}}], "
        f"p={test['wilcoxon_p']:.2g}: {test['verdict']}"
    )


def seed_rows(
    table: Mapping[str, Mapping[str, Mapping[str, object]]], reference: str
) -> tuple[list[str], list[list[str]]]:
    """Header and rows, scene x method: medians as mean +- std over seeds, bands,
    failures and the paired tests."""
    header = [
        "scene",
        "method",
        "median position (m)",
        "median orientation (deg)",
        *(band_title(m, d) for m, d in RECALL_BANDS),
        "failed (per seed)",
        f"position vs {reference}: diff of medians (m) [95% CI], Wilcoxon p",
        f"orientation vs {reference}: diff of medians (deg) [95% CI], Wilcoxon p",
    ]
    rows = []
    for scene, by_method in table.items():
        for method, stats in by_method.items():
            cells = [scene, method]
            for key, fmt in (("median_position_m", ".3f"), ("median_orientation_deg", ".2f")):
                s = stats[key]
                cells.append(f"{s['mean']:{fmt}} +- {s['std']:{fmt}}")
            cells += [f"{stats[band_key(m, d)]['mean']:.1%}" for m, d in RECALL_BANDS]
            cells.append(" ".join(str(n) for n in stats["failed_queries"]))
            tests = stats.get("vs_reference")
            if tests is None:
                cells += ["(reference)", "(reference)"]
            else:
                cells.append(paired_cell(tests["position_m"], ".3f"))
                cells.append(paired_cell(tests["orientation_deg"], ".2f"))
            rows.append(cells)
    return header, rows


def seed_footnote(seeds: Sequence[int], bands: bool = True) -> str:
    """How to read the seed table; `bands=False` for a run without metre bands."""
    banded = " bands are the mean share of queries within both limits." if bands else ""
    return (
        f"\nTraining seeds {', '.join(str(s) for s in seeds)}: medians are mean +- std over "
        f"seeds;{banded} Paired tests use "
        "the same queries: the bootstrap resamples queries (2000 times, the same queries "
        "for both methods on every seed), Wilcoxon tests each query's median over seeds of "
        "its per-seed difference (method minus reference, same seed); p values are not "
        "corrected for the number of methods. A failed query counts as infinitely wrong; "
        "where a method's median is infinite on one seed and the reference's on another, "
        "the difference is undefined and so is the verdict.\n"
    )


def seed_markdown(
    table: Mapping[str, Mapping[str, Mapping[str, object]]], reference: str, seeds: Sequence[int]
) -> str:
    """The seed table in Markdown, with a note on how to read it."""
    return as_markdown(*seed_rows(table, reference)) + seed_footnote(seeds)
