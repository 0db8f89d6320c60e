"""task=compare over training seeds: the spread table and the paired tests."""

import json
from pathlib import Path

import numpy as np
import pytest

from relocfw.core.values import Crop, Localization, Pose
from relocfw.data.frames import Frame
from relocfw.report.evaluation import MethodResult
from relocfw.report.seed_comparison import seed_comparison, seed_markdown
from tests.cli_runs import relocfw, relocfw_here
from tests.conftest import TINY_OVERRIDES

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def answered(method: str, position_errors: list[float]) -> MethodResult:
    """A result whose per-query position errors (m, along x) are as given."""
    truth = Pose(np.zeros(3), IDENTITY)
    frames = tuple(Frame(f"q{i}", Path(f"q{i}.png"), truth) for i in range(len(position_errors)))
    answers = tuple(
        Localization(Pose([e, 0.0, 0.0], IDENTITY), Crop(0, 0, 1), 0.0, 1, 0.0)
        for e in position_errors
    )
    return MethodResult(method, frames, answers)


def test_medians_over_seeds_and_the_paired_test_against_the_reference():
    rng = np.random.default_rng(0)
    errors = {seed: rng.uniform(0.1, 1.0, size=40) for seed in (0, 1, 2)}
    results = {
        seed: {"room": {"Ref": answered("Ref", e), "Half": answered("Half", e / 2)}}
        for seed, e in errors.items()
    }
    floor = answered("mean training pose", [2.0] * 40)
    table = seed_comparison(results, {"room": floor}, "Ref")
    assert list(table["room"]) == ["mean training pose", "Ref", "Half"]
    ref = table["room"]["Ref"]["median_position_m"]
    medians = [np.median(errors[s]) for s in (0, 1, 2)]
    assert ref["values"] == pytest.approx(medians)
    assert ref["std"] == pytest.approx(np.std(medians, ddof=1))
    assert "vs_reference" not in table["room"]["Ref"]
    half = table["room"]["Half"]
    assert half["median_position_m"]["mean"] == pytest.approx(np.mean(medians) / 2)
    assert half["vs_reference"]["position_m"]["verdict"] == "significantly lower"
    assert half["vs_reference"]["orientation_deg"]["verdict"] == "no significant difference"
    worse = table["room"]["mean training pose"]["vs_reference"]["position_m"]
    assert worse["verdict"] == "significantly higher"
    markdown = seed_markdown(table, "Ref", [0, 1, 2])
    assert "| room | Half |" in markdown and "significantly lower" in markdown
    assert "(reference)" in markdown


def test_seeds_must_answer_the_same_queries():
    results = {
        0: {"room": {"Ref": answered("Ref", [0.1, 0.2])}},
        1: {"room": {"Ref": answered("Ref", [0.1, 0.2, 0.3])}},
    }
    with pytest.raises(ValueError, match="other queries"):
        seed_comparison(results, {}, "Ref")


def test_compare_over_two_training_seeds(tmp_path):
    cache = tmp_path / "cache"
    run_dir = tmp_path / "compare"
    methods = '+compare.methods={PoseNet:["crop=centre"],GA:["crop=ga"]}'
    args = [*TINY_OVERRIDES, "task=compare", "~compare.methods", methods]
    args += ["compare.seeds=[0,1]", "compare.crop_seeds=null", f"hydra.run.dir={run_dir}"]
    result = relocfw(args, tmp_path, cache)
    assert result.returncode == 0, result.stderr
    # One model per seed (the two methods share it), trained once each.
    assert result.stdout.count("(trained)") == 2
    report = json.loads((run_dir / "comparison.json").read_text())
    assert report["seeds"] == [0, 1]
    rows = report["scenes"]["synthetic"]
    assert list(rows) == ["mean training pose", "PoseNet", "GA"]
    assert len(rows["GA"]["median_position_m"]["values"]) == 2
    assert rows["GA"]["vs_reference"]["position_m"]["pairs"] == 4
    for seed in (0, 1):
        assert (run_dir / f"seed_{seed}" / "comparison.md").is_file()
        summary = json.loads((run_dir / f"seed_{seed}" / "summary_synthetic.json").read_text())
        assert "within_0.25m_2deg" in summary[0]
    # Different seeds trained different models: their PoseNet medians differ.
    values = rows["PoseNet"]["median_position_m"]["values"]
    assert values[0] != values[1]
    assert "Wilcoxon" in (run_dir / "comparison.md").read_text()


@pytest.mark.parametrize(
    "seeds",
    [
        "compare.seeds=[0,0]",
        "compare.seeds=[]",
        "compare.seeds=[-1]",
        "compare.seeds=3",
        "train.seed=4",
    ],
)
def test_bad_seed_lists_are_refused(tmp_path, seeds):
    args = [*TINY_OVERRIDES, "task=compare", "compare.seeds=[0,1]", seeds]
    result = relocfw_here(args, tmp_path, tmp_path / "cache")
    assert result.returncode != 0
    assert "compare.seeds" in result.stderr and "Traceback" not in result.stderr


def test_a_method_that_fails_queries_is_written_strictly_and_counted(tmp_path):
    import math

    from relocfw.app.tasks.compare import write_comparison, write_seed_comparison

    good = [0.1, 0.2, 0.3, 0.4]
    failing = [0.1, float("nan"), 0.3, float("nan")]  # two queries without a pose
    results = {
        seed: {"room": {"Ref": answered("Ref", good), "Lost": answered("Lost", failing)}}
        for seed in (0, 1)
    }
    floor = answered("mean training pose", [1.0] * 4)
    training = {"room": floor.frames}
    for seed in (0, 1):
        write_comparison(results[seed], training, {}, "Ref", tmp_path / f"seed_{seed}")
    report = write_seed_comparison(results, {"room": floor}, "Ref", tmp_path)
    lost = report["scenes"]["room"]["Lost"]
    assert lost["failed_queries"] == [2, 2]
    assert lost["median_position_m"]["mean"] == pytest.approx((0.3 + math.inf) / 2)
    # Strict JSON everywhere (no NaN / Infinity tokens), failures written as "inf".
    for path in [tmp_path / "comparison.json", *tmp_path.glob("seed_*/*.json")]:
        text = path.read_text()
        assert "Infinity" not in text and "NaN" not in text, path
        json.loads(text)
    summary = json.loads((tmp_path / "seed_0" / "summary_room.json").read_text())
    assert summary[-1]["mean_position_m"] == "inf" and summary[-1]["failed_queries"] == 2
    assert "| room | Lost |" in (tmp_path / "comparison.md").read_text()
    assert "room,Lost," in (tmp_path / "comparison.csv").read_text()
    assert (tmp_path / "seed_0" / "room_position_error_histogram.png").stat().st_size > 0


def test_failures_on_opposite_seeds_print_an_undefined_verdict():
    good = [0.1, 0.2, 0.3, 0.4, 0.5]
    lost = [float("nan")] * 3 + good[3:]  # three of five fail: the median is inf
    results = {
        0: {"room": {"Ref": answered("Ref", good), "Other": answered("Other", lost)}},
        1: {"room": {"Ref": answered("Ref", lost), "Other": answered("Other", good)}},
    }
    table = seed_comparison(results, {}, "Ref")
    test = table["room"]["Other"]["vs_reference"]["position_m"]
    assert test["verdict"].startswith("undefined")
    markdown = seed_markdown(table, "Ref", [0, 1])
    row = next(line for line in markdown.splitlines() if line.startswith("| room | Other |"))
    assert "undefined [-inf, +inf]" in row and "no significant difference" not in row
    assert "per-seed difference" in markdown  # the footnote says what Wilcoxon pairs
