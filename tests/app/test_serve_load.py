"""benchmarks/serve_load.py runs end to end on its tiny smoke model: every answer
arrives and equals task=localize's (the numbers themselves are not checked)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "serve_load.py"


def test_the_load_benchmark_loses_and_changes_no_answer(tmp_path):
    out = tmp_path / "serve_load.json"
    command = [sys.executable, str(SCRIPT), "--smoke", "--clients", "1", "3", "--queries", "2"]
    done = subprocess.run(
        [*command, "--slow-clients", "2", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(out.read_text())
    rows = report["rows"]
    assert [(row["clients"], row["slow_clients"]) for row in rows] == [(1, 0), (3, 0), (3, 2)]
    for row in rows:
        assert row["answered"] == row["queries"] == 2 * row["clients"]
        assert (row["lost"], row["different"], row["refused_503"]) == (0, 0, 0)
        assert row["p99_ms"] >= row["p50_ms"] > 0
    assert "| tiny | 3 | 6/6 | 0 | 0 |" in done.stdout
    assert "| tiny | 3 + 2 slow | 6/6 | 0 | 0 |" in done.stdout


def test_the_load_benchmark_records_what_the_model_ran_with(tmp_path):
    out = tmp_path / "serve_load.json"
    command = [sys.executable, str(SCRIPT), "--smoke", "--clients", "1", "--queries", "1"]
    done = subprocess.run(
        [*command, "--slow-clients", "0", "--serve-override", "serve.body_timeout_s=7"]
        + ["--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    ran = json.loads(out.read_text())["models"]["tiny"]
    assert ran["model_file"]["query"]["crop_samples"] == 0
    assert ran["model_file"]["crop"]["class"].endswith("SweepCrop")
    assert ran["model_file"]["refine"] is None  # the smoke model has no refiner
    assert ran["service"]["refiner"] is None and ran["service"]["backbone"] == "PoseNet"
    serve = ran["serve_settings"]["serve"]
    assert (serve["body_timeout_s"], serve["max_pending"], serve["workers"]) == (7.0, 8, 1)
    assert ran["serve_settings"]["engine"] == "torch"
