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
        [*command, "--out", str(out)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(out.read_text())
    assert [row["clients"] for row in report["rows"]] == [1, 3]
    for row in report["rows"]:
        assert row["answered"] == row["queries"] == 2 * row["clients"]
        assert (row["lost"], row["different"]) == (0, 0)
        assert row["p99_ms"] >= row["p50_ms"] > 0
    assert "| tiny | 3 | 6/6 | 0 | 0 |" in done.stdout
