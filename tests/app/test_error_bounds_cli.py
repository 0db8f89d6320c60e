"""Calibrated error bounds end to end: calibrate.share holds a validation block out of
training and the map, task=relocalize writes each answer's bounds and how often they
held, the model file keeps them, task=localize writes them per frame; and the
calibrate options' refusals."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from relocfw import load_model
from tests.cli_runs import relocfw, relocfw_here
from tests.conftest import TINY_MODEL

# 160 x 120 for SIFT; 36 training frames in recording order, the last 12 held out.
SCENE = [
    "dataset.width=160",
    "dataset.height=120",
    "dataset.train_laps=3",
    "dataset.train_frames_per_lap=12",
    "dataset.test_frames=6",
]
METHOD = ["crop=centre", "index=exhaustive", "refine=features"]


def rows_of(path, method=None):
    with open(path) as stream:
        return [r for r in csv.DictReader(stream) if method is None or r["method"] == method]


def test_bounds_are_calibrated_stored_and_written_by_localize(tmp_path):
    pytest.importorskip("poselib")
    run_dir = tmp_path / "run"
    args = [*TINY_MODEL, *SCENE, *METHOD, "calibrate.share=0.34", f"hydra.run.dir={run_dir}"]
    result = relocfw(args, tmp_path)
    assert result.returncode == 0, result.stderr
    assert "the last 13 training frames" in result.stdout
    assert "90% bounds from 13 validation queries" in result.stdout
    summary = {s["method"]: s for s in json.loads((run_dir / "summary.json").read_text())}
    (method,) = [name for name in summary if "refine_fell_back" in summary[name]]
    row = summary[method]
    # How often the bounds held is measured, not assumed: a share of the 6 queries.
    assert 0.0 <= row["position_bound_coverage"] <= 1.0
    assert row["position_bound_coverage"] * 6 == pytest.approx(
        round(row["position_bound_coverage"] * 6)
    )
    assert row["median_position_bound_m"] > 0
    # The network's own row has no bounds: the calibration belongs to the method.
    assert "position_bound_coverage" not in summary["posenet (centre crop)"]
    # The results say which frames were held out as validation: the last training lap
    # and the frame before it, in recording order.
    block = row["split"]["validation"]["calibration_block"]
    assert block == {
        "frames": 13,
        "first": "seq-02/frame-000011",
        "last": "seq-03/frame-000011",
        "sequences": [2, 3],
    }
    written = rows_of(run_dir / "results.csv", method)
    bounds = [float(r["position_bound_m"]) for r in written]
    assert all(b > 0 for b in bounds) and not any(np.isnan(bounds))
    held = np.mean([float(r["position_error_m"]) <= float(r["position_bound_m"]) for r in written])
    assert held == pytest.approx(row["position_bound_coverage"])
    for r in rows_of(run_dir / "results.csv", "posenet (centre crop)"):
        assert r["position_bound_m"] == "nan"

    model = load_model(run_dir / "model.relocfw")
    assert model.bounds is not None and model.bounds.validation_size == 13
    assert model.bounds.coverage == pytest.approx(0.9)
    assert model.metadata["validation_images"] == 13
    assert model.metadata["map_images"] == 36 - 13

    # task=localize on the test images: the same bounds per frame as the run wrote.
    scene = next((tmp_path / "cache" / "scenes").iterdir())
    sequence = written[0]["frame"].split("/")[0]
    out = tmp_path / "localize"
    localized = relocfw(
        [
            "task=localize",
            f"localize.model={run_dir / 'model.relocfw'}",
            f"localize.images={scene / sequence}/*.color.png",
            f"hydra.run.dir={out}",
            "quiet=true",
        ],
        tmp_path,
    )
    assert localized.returncode == 0, localized.stderr
    assert "error bounds: 90% bounds from 13 validation queries" in localized.stdout
    answers = rows_of(out / "localization.csv")
    assert len(answers) == len(written)
    for answer, row in zip(answers, written, strict=True):
        assert float(answer["position_bound_m"]) == pytest.approx(float(row["position_bound_m"]))
        assert float(answer["orientation_bound_deg"]) == pytest.approx(
            float(row["orientation_bound_deg"])
        )


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (
            "calibrate.share=0.05",
            "calibrate.share=0.05 holds out 2 of the 36 training frames; "
            "at least 10 are needed to calibrate 90% error bounds",
        ),
        ("calibrate.share=0.8", "calibrate.share must be above 0 and at most 0.5, got 0.8"),
        ("calibrate.share=-0.1", "calibrate.share must be above 0 and at most 0.5"),
        (
            "calibrate.coverage=1.5",
            "calibrate.coverage must be between 0.5 and 0.999 (e.g. 0.9), got 1.5",
        ),
        ("calibrate.bins=0", "calibrate.bins must be at least 1, got 0"),
    ],
)
def test_impossible_calibrate_options_are_refused_before_training(tmp_path, option, message):
    extra = [] if option.startswith("calibrate.share") else ["calibrate.share=0.34"]
    result = relocfw_here([*TINY_MODEL, *SCENE, *METHOD, *extra, option], tmp_path)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert not (tmp_path / "cache" / "checkpoints").exists()
