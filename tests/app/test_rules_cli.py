"""methods=rules: the selection rules as crop=rule rows of task=compare, end to end."""

import csv
import itertools
import json
from pathlib import Path

from tests.cli_runs import relocfw
from tests.conftest import TINY_OVERRIDES


def test_compare_runs_the_rule_rows_on_one_model(tmp_path):
    run_dir = tmp_path / "compare"
    args = [*TINY_OVERRIDES, "task=compare", "methods=rules", "compare.crop_seeds=null"]
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 0, result.stderr
    # One model for every row: the rules only change how a query is answered.
    assert result.stdout.count("(trained)") == 1
    summary = json.loads((run_dir / "summary_synthetic.json").read_text())
    rows = {row["method"]: row for row in summary}
    for name in ("PoseNet", "Mean of all windows", "Robust mean pose", "Consensus window"):
        assert name in rows, sorted(rows)
    # Every window is scored, as by the sweep: the same crops per query.
    sweep = rows["Min map distance (sweep)"]
    assert rows["Mean of all windows"]["mean_crops_scored"] == sweep["mean_crops_scored"]
    # A blend is its own answer, not the centre crop's.
    assert rows["Mean of all windows"]["median_position_m"] != rows["PoseNet"]["median_position_m"]
    answers = answers_by_frame(run_dir / "results_synthetic.csv")
    assert len(answers) == 4
    for frame, methods in answers.items():
        # Every rule row scores every window and reports one window's distance (the
        # blends the window nearest their pose): none is below the sweep's minimum.
        nearest = methods["Min map distance (sweep)"]["distance"]
        assert all(m["distance"] >= nearest for m in methods.values() if m["crop"]), frame
        # Rows that report the same window report its distance, and those that answer
        # with a window's own pose (not a blend) report the same pose.
        for one, other in itertools.combinations(methods, 2):
            a, b = methods[one], methods[other]
            if a["crop"] == b["crop"] and a["crop"]:
                assert a["distance"] == b["distance"], (frame, one, other)
                if one in WINDOW_ROWS and other in WINDOW_ROWS:
                    assert a["pose"] == b["pose"], (frame, one, other)
    # Each rule answers as its own: no two rows give the same answers on every frame.
    runs = {name: tuple(answers[f][name]["pose"] for f in sorted(answers)) for name in rows}
    assert len(set(runs.values())) == len(runs), runs


# The rows whose answer is one window's own network pose: the rest blend windows.
WINDOW_ROWS = ("PoseNet", "Min map distance (sweep)", "Consensus window", "Retrieval consistency")


def answers_by_frame(path: Path) -> dict[str, dict[str, dict]]:
    """results CSV -> frame -> method -> its estimated pose (the CSV's digits), its
    crop (None where it has none) and its map distance."""
    answers: dict[str, dict[str, dict]] = {}
    with open(path) as stream:
        for row in csv.DictReader(stream):
            crop = tuple(int(row[f"crop_{c}"]) for c in ("x", "y", "size"))
            answers.setdefault(row["frame"], {})[row["method"]] = {
                "pose": tuple(row[f"est_{c}"] for c in ("x", "y", "z", "qw", "qx", "qy", "qz")),
                "crop": crop if crop[2] > 0 else None,
                "distance": float(row["distance"]),
            }
    return answers


def test_a_rule_with_shared_scoring_is_refused_before_any_training(tmp_path):
    from tests.cli_runs import relocfw_here

    result = relocfw_here([*TINY_OVERRIDES, "crop=rule", "query.scoring=shared"], tmp_path)
    assert result.returncode == 2, result.stderr
    assert "scoring=plain" in result.stderr and "Traceback" not in result.stderr
    assert not list((tmp_path / "cache").glob("checkpoints/*.pt"))  # nothing was trained
