"""benchmarks/paired_runs.py: rows of two compare runs paired query by query, with
each row's per-seed costs read from the runs' summaries."""

from __future__ import annotations

import csv
import importlib
import json
from pathlib import Path

import pytest

from relocfw.core.errors import DataError

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture
def paired_runs(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    return importlib.import_module("paired_runs")


def write_run(folder: Path, rows: dict[str, list[float]], ms: dict[str, float]) -> Path:
    """A compare run of seeds 0 and 1: each row's position errors (orientation 1 deg)
    on the same frames, and its median seconds per query in the summary."""
    for seed in (0, 1):
        seed_folder = folder / f"seed_{seed}"
        seed_folder.mkdir(parents=True)
        with (seed_folder / "results_room.csv").open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(
                ["method", "frame", "position_error_m", "orientation_error_deg", "fell_back"]
            )
            for method, errors in rows.items():
                for number, error in enumerate(errors):
                    writer.writerow([method, f"frame-{number}", error + seed * 1e-4, 1.0, 0])
        summary = [
            {
                "method": method,
                "median_seconds_per_query": ms[method] / 1000 + seed * 0.001,
                "refine_median_ms_solve": 3.0 + seed,
            }
            for method in rows
        ]
        (seed_folder / "summary_room.json").write_text(json.dumps(summary))
    return folder


def test_a_pair_holds_its_test_and_each_rows_costs(paired_runs, tmp_path):
    old = [0.04 + 0.001 * k for k in range(30)]
    new = [error - 0.01 for error in old]
    run = write_run(tmp_path / "run", {"new": new, "old": old}, {"new": 20.0, "old": 30.0})
    result = paired_runs.compare_pair((run, "new"), (run, "old"))
    assert result["seeds"] == [0, 1]
    assert result["position_m"]["verdict"] == "significantly lower"
    # 0.03 + 0.001 k is within 5 cm for k <= 20 (seed 1 adds 0.1 mm: k <= 19).
    assert result["new"]["within_5cm_5deg"] == pytest.approx([21 / 30, 20 / 30], abs=1e-4)
    assert result["new"]["costs"]["median_ms"] == [20.0, 21.0]
    assert result["old"]["costs"]["median_ms"] == [30.0, 31.0]
    assert result["new"]["costs"]["refine_median_ms_solve"] == [3.0, 4.0]


def test_rows_that_answered_other_queries_are_an_error(paired_runs, tmp_path):
    run = write_run(tmp_path / "a", {"row": [0.1, 0.2]}, {"row": 5.0})
    other = write_run(tmp_path / "b", {"row": [0.1, 0.2, 0.3]}, {"row": 5.0})
    with pytest.raises(DataError, match="different queries"):
        paired_runs.compare_pair((run, "row"), (other, "row"))


def test_a_run_without_summaries_pairs_without_costs(paired_runs, tmp_path):
    run = write_run(
        tmp_path / "run", {"a": [0.1, 0.2, 0.3], "b": [0.2, 0.3, 0.4]}, {"a": 1, "b": 1}
    )
    for summary in run.glob("seed_*/summary_*.json"):
        summary.unlink()
    result = paired_runs.compare_pair((run, "a"), (run, "b"))
    assert result["new"]["costs"] == {} and result["old"]["costs"] == {}


def test_runs_scored_against_other_references_are_not_paired(paired_runs, tmp_path):
    """The same frame names under another pose reference carry other truths."""
    record = {
        "test_sequences": [2, 4, 6],
        "pose_reference": {"kind": "pgt", "file": "sfm.txt", "sha256": "aa"},
    }
    other = {**record, "pose_reference": {"kind": "pgt", "file": "dslam.txt", "sha256": "bb"}}
    paired_runs.check_same_scoring(tmp_path / "a", tmp_path / "b", record, dict(record))
    paired_runs.check_same_scoring(tmp_path / "a", tmp_path / "b", record, None)
    with pytest.raises(DataError, match="score against other pose references"):
        paired_runs.check_same_scoring(tmp_path / "a", tmp_path / "b", record, other)
    with pytest.raises(DataError, match=r"test_sequences \[2, 4, 6\] against \[5, 6, 7\]"):
        paired_runs.check_same_scoring(
            tmp_path / "a", tmp_path / "b", record, {**record, "test_sequences": [5, 6, 7]}
        )
