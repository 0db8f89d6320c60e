"""methods=rules: the selection rules as crop=rule rows of task=compare, end to end."""

import json

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


def test_a_rule_with_shared_scoring_is_refused_before_any_training(tmp_path):
    from tests.cli_runs import relocfw_here

    result = relocfw_here([*TINY_OVERRIDES, "crop=rule", "query.scoring=shared"], tmp_path)
    assert result.returncode == 2, result.stderr
    assert "scoring=plain" in result.stderr and "Traceback" not in result.stderr
    assert not list((tmp_path / "cache").glob("checkpoints/*.pt"))  # nothing was trained
