"""task=compare over several training seeds: each method's spread, paired tests, and
the quality of each method's uncertainty signal (spread or refiner confidence)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from relocfw.report.comparison import as_markdown
from relocfw.report.evaluation import MethodResult, bound_columns, uncertainty_of
from relocfw.report.metrics import RECALL_BANDS, accuracy_metrics, band_key, band_title
from relocfw.report.statistics import paired_test, spread
from relocfw.report.uncertainty import REJECTION_SHARES

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


def uncertainty_statistics(by_seed: Sequence[MethodResult]) -> dict[str, object] | None:
    """One method's uncertainty measures over seeds; None when no seed has a signal.

    `signal` names what ranks the queries (relocfw.report.evaluation
    .uncertainty_signal_of; seeds that disagree are joined with " / "). Per kind:
    `spearman_uncertainty_error` per seed (a correlation's sign can flip from one
    seed to the next, which a mean would hide), and the spread over seeds of `ause`
    and of each `median_after_rejecting` share. A seed without a signal counts as NaN.
    """
    measured = [uncertainty_of(result) for result in by_seed]
    if all(m is None for m in measured):
        return None
    names = dict.fromkeys(m[0].name for m in measured if m is not None)
    statistics: dict[str, object] = {"signal": " / ".join(names)}
    nan = float("nan")
    for kind in ("position", "orientation"):
        qualities = [None if m is None else m[1][kind] for m in measured]
        statistics[kind] = {
            "spearman_uncertainty_error": [
                nan if q is None else q["spearman_uncertainty_error"] for q in qualities
            ],
            "ause": spread([nan if q is None else q["ause"] for q in qualities]),
            "median_after_rejecting": {
                f"{share:.0%}": spread(
                    [
                        nan if q is None else q["median_after_rejecting"][f"{share:.0%}"]
                        for q in qualities
                    ]
                )
                for share in REJECTION_SHARES
            },
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
        for method in by_method:
            # The floor has no signal; only rows with one get the key.
            uncertainty = uncertainty_statistics([results[s][scene][method] for s in seeds])
            if uncertainty is not None:
                table[scene][method]["uncertainty"] = uncertainty
            bounds = bound_statistics([results[s][scene][method] for s in seeds])
            if bounds is not None:
                table[scene][method]["bounds"] = bounds
    return table


def bound_statistics(by_seed: Sequence[MethodResult]) -> dict[str, list[float]] | None:
    """Per seed, how often the calibrated error bounds held on the queries and their
    medians (relocfw.report.evaluation.bound_columns); None when no seed has bounds."""
    columns = [bound_columns(result) for result in by_seed]
    if not any(columns):
        return None
    nan = float("nan")
    keys = (
        "position_bound_coverage",
        "orientation_bound_coverage",
        "median_position_bound_m",
        "median_orientation_bound_deg",
    )
    return {key: [c.get(key, nan) for c in columns] for key in keys}


def bound_cells(bounds: Mapping[str, list[float]] | None) -> list[str]:
    """A row's BOUND_TITLES cells: "-" for a method without bounds."""
    if bounds is None:
        return ["-", "-"]
    held = "/".join(
        f"{p:.0%} {o:.0%}"
        for p, o in zip(
            bounds["position_bound_coverage"], bounds["orientation_bound_coverage"], strict=True
        )
    )
    medians = "/".join(
        f"{p:.3f} m {o:.1f} deg"
        for p, o in zip(
            bounds["median_position_bound_m"], bounds["median_orientation_bound_deg"], strict=True
        )
    )
    return [held, medians]


BOUND_TITLES = [
    "bounds held: position, orientation (per seed)",
    "median bound (per seed)",
]


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


SHARES_TITLE = "/".join(f"{100 * share:g}" for share in REJECTION_SHARES)  # "10/20/30"
UNCERTAINTY_TITLES = (
    "uncertainty signal",
    "Spearman pos (per seed)",
    "Spearman ori (per seed)",
    "AUSE pos (m)",
    "AUSE ori (deg)",
    f"median pos after rejecting {SHARES_TITLE} % (m)",
    f"median ori after rejecting {SHARES_TITLE} % (deg)",
)


def signed(correlation: float) -> str:
    """A correlation with its sign ("+0.42"); "nan" where it is undefined."""
    return f"{correlation:+.2f}" if np.isfinite(correlation) else "nan"


def uncertainty_cells(uncertainty: Mapping[str, object] | None) -> list[str]:
    """A row's UNCERTAINTY_TITLES cells: "-" throughout for a method without a signal."""
    if uncertainty is None:
        return ["-"] * len(UNCERTAINTY_TITLES)
    cells = [str(uncertainty["signal"])]
    for kind in ("position", "orientation"):
        cells.append("/".join(signed(r) for r in uncertainty[kind]["spearman_uncertainty_error"]))
    for kind, fmt in (("position", ".3f"), ("orientation", ".2f")):
        cells.append(f"{uncertainty[kind]['ause']['mean']:{fmt}}")
    for kind, fmt in (("position", ".3f"), ("orientation", ".2f")):
        medians = uncertainty[kind]["median_after_rejecting"].values()
        cells.append("/".join(f"{m['mean']:{fmt}}" for m in medians))
    return cells


def seed_rows(
    table: Mapping[str, Mapping[str, Mapping[str, object]]], reference: str
) -> tuple[list[str], list[list[str]]]:
    """Header and rows, scene x method: medians as mean +- std over seeds, bands,
    failures and the paired tests; then, when any method has an uncertainty signal
    (a sampled spread or a refiner's confidence), which signal each row uses and its
    measures (UNCERTAINTY_TITLES: Spearman per seed, the rest means over seeds)."""
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
    # A table without any signal keeps its columns as they were.
    measured = [
        stats.get("uncertainty") for by_method in table.values() for stats in by_method.values()
    ]
    if any(m is not None for m in measured):
        header += UNCERTAINTY_TITLES
        rows = [row + uncertainty_cells(m) for row, m in zip(rows, measured, strict=True)]
    bounded = [stats.get("bounds") for by_method in table.values() for stats in by_method.values()]
    if any(b is not None for b in bounded):
        header += BOUND_TITLES
        rows = [row + bound_cells(b) for row, b in zip(rows, bounded, strict=True)]
    return header, rows


UNCERTAINTY_FOOTNOTE = (
    "The uncertainty columns rank each method's queries by its signal: a sampled "
    "method's spread, or a refined method's confidence (less confident is more "
    "uncertain; fallbacks the most uncertain). Spearman of uncertainty with error is "
    "per seed and positive for a useful signal; AUSE (over the queries with a finite "
    "error, 0: ranked as the errors are) and the medians after rejecting the most "
    "uncertain queries are means over seeds.\n"
)


def seed_footnote(seeds: Sequence[int], bands: bool = True, uncertainty: bool = False) -> str:
    """How to read the seed table; `bands=False` for a run without metre bands,
    `uncertainty=True` for one with uncertainty columns."""
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
    ) + (UNCERTAINTY_FOOTNOTE if uncertainty else "")


def seed_markdown(
    table: Mapping[str, Mapping[str, Mapping[str, object]]], reference: str, seeds: Sequence[int]
) -> str:
    """The seed table in Markdown, with a note on how to read it."""
    measured = any("uncertainty" in stats for rows in table.values() for stats in rows.values())
    return as_markdown(*seed_rows(table, reference)) + seed_footnote(seeds, uncertainty=measured)
