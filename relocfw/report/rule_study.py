"""Which test-time selection rule beats the centre crop? Settings from validation only.

Input: for each training seed, the recorded windows (relocfw.report.window_recording)
of a validation block carved from the training data (diagnosed with a model trained
without it) and of the test split (diagnosed with the model trained on all training
data). Every rule's setting (temperature, threshold, the learned selector) is chosen
on the validation recordings alone; the test recordings are then answered once per
rule and compared with the centre crop per seed and query (the project's paired
Wilcoxon + bootstrap, relocfw.report.statistics). The oracle window (chosen with the
ground truth) bounds what any choice of window can gain: `headroom_captured` is the
share of the centre-to-oracle gap in median position a rule closes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from relocfw.core.window_rules import (
    Choice,
    LearnedSelector,
    Windows,
    gated,
    rule_named,
    soft_min_distance,
    window_choice,
)
from relocfw.report.figures import new_figure, save
from relocfw.report.seed_comparison import method_statistics
from relocfw.report.window_recording import RecordedQuery

TEMPERATURES = (0.003, 0.01, 0.03, 0.1, 0.3, 1.0)
GATE_QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9)  # of the validation queries' nearest distance
REFERENCE = "centre"
ORACLE = "oracle (position)"


def answer_all(rule: Callable[[Windows], Choice], queries: Sequence[RecordedQuery]) -> np.ndarray:
    """[2, N] position and orientation errors of a rule's answers."""
    errors = [q.errors(*_pose(rule(q.windows))) for q in queries]
    return np.array(errors, dtype=np.float64).T


def _pose(choice: Choice) -> tuple[np.ndarray, np.ndarray]:
    return choice.position, choice.quaternion


def oracle(query: RecordedQuery) -> Choice:
    """The window of smallest position error (orientation breaks ties)."""
    position, orientation = query.window_errors()
    return window_choice(query.windows, int(np.lexsort((orientation, position))[0]))


def pooled_median(rule: Callable[[Windows], Choice], seeds: Sequence[Sequence[RecordedQuery]]):
    """Median position error of a rule over every seed's validation queries."""
    return float(np.median(np.concatenate([answer_all(rule, qs)[0] for qs in seeds])))


@dataclass(frozen=True)
class ChosenSettings:
    """Each tuned rule's setting, with the validation medians it was chosen by."""

    temperature: float
    gate_threshold: float
    temperature_scores: dict[str, float]
    gate_scores: dict[str, float]


def choose_settings(validation: Sequence[Sequence[RecordedQuery]]) -> ChosenSettings:
    """The temperature and gate threshold of smallest pooled median position error
    on the validation recordings (every seed's)."""
    temperature_scores = {
        f"{tau:g}": pooled_median(lambda w, tau=tau: soft_min_distance(w, tau), validation)
        for tau in TEMPERATURES
    }
    nearest = np.concatenate(
        [[q.windows.relative_distances.min() for q in seed] for seed in validation]
    )
    thresholds = np.quantile(nearest, GATE_QUANTILES)
    gate_scores = {
        f"{t:.6g}": pooled_median(lambda w, t=t: gated(w, t), validation) for t in thresholds
    }
    return ChosenSettings(
        temperature=float(min(temperature_scores, key=temperature_scores.get)),
        gate_threshold=float(min(gate_scores, key=gate_scores.get)),
        temperature_scores=temperature_scores,
        gate_scores=gate_scores,
    )


def fitted_selector(queries: Sequence[RecordedQuery], seed: int) -> LearnedSelector:
    """A LearnedSelector fitted on one seed's validation recording."""
    return LearnedSelector(seed=seed).fit(
        [q.windows for q in queries],
        [q.window_errors()[0] for q in queries],
        [q.frame for q in queries],
    )


def rules_of(settings: ChosenSettings, selector: LearnedSelector) -> dict[str, Callable]:
    """Every rule the study answers with, by its table name."""
    return {
        REFERENCE: rule_named("centre"),
        "min map distance (paper)": rule_named("min_distance"),
        f"soft min distance (tau={settings.temperature:g})": rule_named(
            "soft_min_distance", tau=settings.temperature
        ),
        "mean of all windows": rule_named("mean"),
        "robust mean pose": rule_named("robust_mean"),
        "consensus window": rule_named("consensus"),
        "retrieval consistency": rule_named("retrieval_consistency"),
        "learned selector": selector,
        f"gated (threshold={settings.gate_threshold:.3g})": rule_named(
            "gated", threshold=settings.gate_threshold
        ),
    }


def study(
    validation: Mapping[int, Sequence[RecordedQuery]],
    test: Mapping[int, Sequence[RecordedQuery]],
    bootstrap_seed: int = 0,
) -> dict[str, Any]:
    """The rules table of one (backbone, split): settings from `validation`, errors on
    `test`, per training seed (both maps keyed by seed, same seeds).

    Raises:
        ValueError: the seeds differ, a seed's test queries differ from another's, or
            a validation frame is also a test frame (the carve leaked).
    """
    seeds = sorted(test)
    if sorted(validation) != seeds:
        raise ValueError(f"validation seeds {sorted(validation)} differ from test seeds {seeds}")
    names = [q.frame for q in test[seeds[0]]]
    for seed in seeds:
        if [q.frame for q in test[seed]] != names:
            raise ValueError(f"seed {seed} answered other test queries than seed {seeds[0]}")
        leaked = {q.frame for q in validation[seed]} & set(names)
        if leaked:
            raise ValueError(f"validation frames are test frames: {sorted(leaked)[:3]}")
    settings = choose_settings([validation[s] for s in seeds])
    selectors = {s: fitted_selector(validation[s], s) for s in seeds}
    # Which rules win on validation (the learned selector left out: it was fitted there).
    on_validation = {
        name: pooled_median(rule, [validation[s] for s in seeds])
        for name, rule in rules_of(settings, selectors[seeds[0]]).items()
        if name != "learned selector"
    }
    errors: dict[str, list[np.ndarray]] = {}
    labels: list[str] = []
    for seed in seeds:
        selector = selectors[seed]
        if set(selector.fitted_on) & set(names):  # fit's own record, checked again
            raise ValueError("the learned selector saw a test query")
        for name, rule in rules_of(settings, selector).items():
            errors.setdefault(name, []).append(answer_all(rule, test[seed]))
            if name not in labels:
                labels.append(name)
        errors.setdefault(ORACLE, []).append(oracle_errors(test[seed]))
    labels.append(ORACLE)
    stacked = {name: np.stack(rows) for name, rows in errors.items()}  # [S, 2, N]
    centre = stacked[REFERENCE]
    centre_median = np.median(centre[:, 0], axis=1).mean()
    oracle_median = np.median(stacked[ORACLE][:, 0], axis=1).mean()
    table = {}
    for name in labels:
        e = stacked[name]
        statistics = method_statistics(
            e[:, 0],
            e[:, 1],
            None if name == REFERENCE else (centre[:, 0], centre[:, 1]),
            bootstrap_seed,
        )
        gap = centre_median - oracle_median
        median = np.median(e[:, 0], axis=1).mean()
        statistics["headroom_captured"] = float((centre_median - median) / gap) if gap else 0.0
        table[name] = statistics
    return {
        "seeds": seeds,
        "test_queries": len(names),
        "validation_queries": {str(s): len(validation[s]) for s in seeds},
        "settings": {
            "temperature": settings.temperature,
            "gate_threshold": settings.gate_threshold,
            "validation_median_position_m": {
                "temperature": settings.temperature_scores,
                "gate_threshold": settings.gate_scores,
            },
        },
        "learned_selector_fitted_on": {str(s): len(selectors[s].fitted_on) for s in seeds},
        "validation_median_position_m": on_validation,
        "rules": table,
    }


def oracle_errors(queries: Sequence[RecordedQuery]) -> np.ndarray:
    """[2, N] errors of the oracle window (it needs each query's truth)."""
    return np.array([q.errors(*_pose(oracle(q))) for q in queries], dtype=np.float64).T


def spread_cell(value: Mapping[str, Any], digits: int) -> str:
    return f"{value['mean']:.{digits}f} +- {value['std']:.{digits}f}"


def paired_text(test: Mapping[str, Any], digits: int) -> str:
    low, high = test["bootstrap_95"]
    return (
        f"{test['median_difference']:+.{digits}f} [{low:+.{digits}f}, {high:+.{digits}f}] "
        f"p={test['wilcoxon_p']:.2g}, {test['verdict']}"
    )


def as_markdown(title: str, report: Mapping[str, Any]) -> str:
    """The rules table: medians over seeds, paired test against the centre crop."""
    lines = [
        f"## {title}: {report['test_queries']} test queries, seeds "
        f"{', '.join(map(str, report['seeds']))}",
        "",
        "| rule | median pos (m) | median ori (deg) | 25cm/2deg | 50cm/5deg "
        "| pos vs centre (m) | ori vs centre (deg) | headroom captured |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, row in report["rules"].items():
        versus = row.get("vs_reference")
        lines.append(
            f"| {name} | {spread_cell(row['median_position_m'], 3)} "
            f"| {spread_cell(row['median_orientation_deg'], 2)} "
            f"| {row['within_0.25m_2deg']['mean']:.1%} | {row['within_0.5m_5deg']['mean']:.1%} "
            f"| {paired_text(versus['position_m'], 3) if versus else 'reference'} "
            f"| {paired_text(versus['orientation_deg'], 2) if versus else 'reference'} "
            f"| {row['headroom_captured']:.0%} |"
        )
    settings = report["settings"]
    validation = report["validation_median_position_m"]
    lines += [
        "",
        "On validation (every seed's validation block pooled), median position (m): "
        + ", ".join(f"{name} {value:.3f}" for name, value in validation.items())
        + ".",
        "",
        f"Chosen on validation only: temperature {settings['temperature']:g}, gate threshold "
        f"{settings['gate_threshold']:.3g} (map-image units); the learned selector was fitted "
        "on each seed's validation windows ("
        + ", ".join(f"seed {s}: {n}" for s, n in report["learned_selector_fitted_on"].items())
        + " queries).",
    ]
    return "\n".join(lines) + "\n"


def headroom_figure(reports: Mapping[str, Mapping[str, Any]], path: Path) -> Path:
    """One bar group per (backbone, split): the share of the oracle headroom each rule
    captures (negative: worse than the centre crop)."""
    titles = list(reports)
    rules = [r for r in next(iter(reports.values()))["rules"] if r not in (REFERENCE, ORACLE)]
    short = [r.split(" (")[0] for r in rules]
    figure, axes = new_figure((1.6 + 0.9 * len(rules), 4.2))
    width = 0.8 / max(len(titles), 1)
    for j, title in enumerate(titles):
        values = [
            next(
                row["headroom_captured"]
                for name, row in reports[title]["rules"].items()
                if name.split(" (")[0] == rule
            )
            for rule in short
        ]
        axes.bar(np.arange(len(rules)) + j * width, 100 * np.array(values), width, label=title)
    axes.axhline(0, color="black", linewidth=0.8)
    axes.set_xticks(np.arange(len(rules)) + 0.4 - width / 2, short, rotation=30, ha="right")
    axes.set_ylabel("oracle headroom captured (% of centre -> oracle, median position)")
    axes.legend(fontsize=8)
    return save(figure, path)
