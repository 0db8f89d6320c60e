"""The Table-1 style comparison: scenes x methods, median errors, error decrease."""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence

import numpy as np

from relocfw.report.evaluation import MethodResult, uncertainty_signal_of
from relocfw.report.statistics import spearman
from relocfw.report.units import METRES, PositionUnit

AVERAGE = "average"


def error_decrease(reference: float, value: float) -> float:
    """How much lower `value` is than `reference`, in percent (negative: higher); an
    infinite error (failed queries) counts as infinitely high."""
    if reference == value:
        return 0.0  # both zero, or both failed (inf)
    if reference == 0 or np.isinf(value):
        return float("-inf")
    if np.isinf(reference):
        return 100.0  # the reference failed, the method did not
    return 100.0 * (reference - value) / reference


def median_errors(
    results: Mapping[str, Mapping[str, MethodResult]],
) -> dict[str, dict[str, tuple[float, float]]]:
    """scene -> method -> (median position error, median orientation deg), plus an average row.

    The average row is the mean over scenes of the per-scene medians, as in the
    paper's tables (not the median over all queries pooled).
    """
    table = {
        scene: {
            method: (
                float(np.median(result.position_errors())),
                float(np.median(result.orientation_errors())),
            )
            for method, result in by_method.items()
        }
        for scene, by_method in results.items()
    }
    methods = list(next(iter(table.values())))
    table[AVERAGE] = {
        method: (
            float(np.mean([table[s][method][0] for s in results])),
            float(np.mean([table[s][method][1] for s in results])),
        )
        for method in methods
    }
    return table


def table_rows(
    table: Mapping[str, Mapping[str, tuple[float, float]]],
    reference: str,
    unit: PositionUnit = METRES,
) -> tuple[list[str], list[list[str]]]:
    """Header and rows: each method's medians (position in `unit`, orientation in
    degrees), then each other method's decrease."""
    methods = list(next(iter(table.values())))
    if reference not in methods:
        raise KeyError(f"compare.reference {reference!r} is not one of the methods {methods}")
    others = [m for m in methods if m != reference]
    header = ["scene", *(f"{m} ({unit.name}, deg)" for m in methods)]
    header += [f"{m} decrease vs {reference} (pos %, ori %)" for m in others]
    rows = []
    for scene, by_method in table.items():
        row = [scene] + [f"{p:.3f}, {o:.2f}" for p, o in by_method.values()]
        ref_p, ref_o = by_method[reference]
        for method in others:
            p, o = by_method[method]
            row.append(f"{error_decrease(ref_p, p):.1f}, {error_decrease(ref_o, o):.1f}")
        rows.append(row)
    return header, rows


def as_markdown(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def as_csv(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    stream = io.StringIO()
    writer = csv.writer(stream)
    writer.writerow(header)
    writer.writerows(rows)
    return stream.getvalue()


def uncertainty_check(
    result: MethodResult, share: float = 0.25
) -> dict[str, float | int | str] | None:
    """Median errors of the most and least uncertain queries (Bayesian PoseNet, or a
    refiner's confidence).

    A useful uncertainty ranks queries by error: the top `share` by the position
    uncertainty (relocfw.report.evaluation.uncertainty_signal_of: the spread, or the
    refiner's lack of confidence) should have larger errors than the bottom `share`.
    `uncertainty_signal` names it. None when the method has no such signal.
    """
    signal = uncertainty_signal_of(result)
    if signal is None:
        return None
    spread = signal.position
    order = np.argsort(spread)
    count = max(1, int(round(share * len(order))))
    low, high = order[:count], order[-count:]
    positions, orientations = result.position_errors(), result.orientation_errors()
    return {
        "uncertainty_signal": signal.name,
        "queries_per_group": count,
        "least_uncertain_median_position_m": float(np.median(positions[low])),
        "most_uncertain_median_position_m": float(np.median(positions[high])),
        "least_uncertain_median_orientation_deg": float(np.median(orientations[low])),
        "most_uncertain_median_orientation_deg": float(np.median(orientations[high])),
        # A missing value ranks as the most uncertain, as in relocfw.report.uncertainty.
        "spread_error_rank_correlation": spearman(
            np.where(np.isnan(spread), np.inf, spread), positions
        ),
    }


def crop_seed_spread(by_seed: Mapping[int, MethodResult]) -> dict[str, object]:
    """How much a randomised crop search's medians move with its own seed.

    Args:
        by_seed: the same method, model and map run with each crop-search seed.

    Returns:
        The seeds, each seed's median position (m) and orientation (deg) errors, and
        their mean, sample standard deviation, minimum and maximum.
    """
    seeds = sorted(by_seed)
    positions = np.array([np.median(by_seed[s].position_errors()) for s in seeds])
    orientations = np.array([np.median(by_seed[s].orientation_errors()) for s in seeds])

    def spread(values: np.ndarray) -> dict[str, float]:
        return {
            "mean": float(values.mean()),
            "std": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
            "min": float(values.min()),
            "max": float(values.max()),
        }

    return {
        "seeds": seeds,
        "median_position_m": positions.tolist(),
        "median_orientation_deg": orientations.tolist(),
        "median_position_m_spread": spread(positions),
        "median_orientation_deg_spread": spread(orientations),
    }


def crop_seed_markdown(
    spreads: Mapping[str, Mapping[str, Mapping[str, object]]], unit: PositionUnit = METRES
) -> str:
    """scene x method table of the medians' mean +- std (min - max) over crop seeds."""
    header = [
        "scene",
        "method",
        "crop seeds",
        f"median position ({unit.name})",
        "median orientation (deg)",
    ]
    rows = []
    for scene, by_method in spreads.items():
        for method, spread in by_method.items():
            cells = [scene, method, " ".join(str(s) for s in spread["seeds"])]
            for key, fmt in (("median_position_m", ".3f"), ("median_orientation_deg", ".2f")):
                s = spread[f"{key}_spread"]
                cells.append(
                    f"{s['mean']:{fmt}} +- {s['std']:{fmt}} ({s['min']:{fmt}} - {s['max']:{fmt}})"
                )
            rows.append(cells)
    return as_markdown(header, rows)
