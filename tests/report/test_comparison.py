import numpy as np
import pytest

from relocfw.core.values import Crop, Localization, Pose
from relocfw.data.frames import Frame
from relocfw.report import figures
from relocfw.report.comparison import (
    as_csv,
    as_markdown,
    crop_seed_markdown,
    crop_seed_spread,
    error_decrease,
    median_errors,
    table_rows,
    uncertainty_check,
)
from relocfw.report.evaluation import MethodResult


def frames(n):
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return tuple(
        Frame(f"seq-01/frame-{i:06d}", None, Pose([np.cos(a), np.sin(a), 1.0], [1, 0, 0, 0]))
        for i, a in enumerate(angles)
    )


def result(method, truth, offset, spreads=None):
    answers = []
    for i, frame in enumerate(truth):
        spread = float("nan") if spreads is None else spreads[i]
        pose = Pose(frame.pose.position + [offset * (i + 1), 0, 0], [1, 0, 0, 0])
        answers.append(Localization(pose, Crop(0, 0, 10), 1.0, 3, 0.01, spread, spread))
    return MethodResult(method, truth, tuple(answers))


def test_error_decrease_arithmetic():
    assert error_decrease(2.0, 1.5) == pytest.approx(25.0)
    assert error_decrease(1.0, 1.2) == pytest.approx(-20.0)
    assert error_decrease(0.0, 0.0) == 0.0
    inf = float("inf")  # failed queries: an infinitely high error
    assert error_decrease(1.0, inf) == -inf
    assert error_decrease(inf, 1.0) == 100.0
    assert error_decrease(inf, inf) == 0.0


def test_table_rows_and_average():
    truth = frames(4)
    scene_a = {"PoseNet": result("PoseNet", truth, 0.2), "Ours": result("Ours", truth, 0.1)}
    scene_b = {"PoseNet": result("PoseNet", truth, 0.4), "Ours": result("Ours", truth, 0.1)}
    table = median_errors({"a": scene_a, "b": scene_b})
    # Position errors 0.1*(1..4): median 0.25; 0.2*(1..4): 0.5; 0.4*(1..4): 1.0.
    assert table["a"]["PoseNet"][0] == pytest.approx(0.5)
    assert table["a"]["Ours"][0] == pytest.approx(0.25)
    assert table["average"]["PoseNet"][0] == pytest.approx(0.75)  # mean of the medians
    header, rows = table_rows(table, "PoseNet")
    assert header[-1] == "Ours decrease vs PoseNet (pos %, ori %)"
    assert rows[0] == ["a", "0.500, 0.00", "0.250, 0.00", "50.0, 0.0"]
    assert rows[2][-1] == "66.7, 0.0"  # (0.75 - 0.25) / 0.75
    assert as_markdown(header, rows).count("\n") == 5
    assert as_csv(header, rows).splitlines()[1].startswith("a,")
    with pytest.raises(KeyError, match="Bayes"):
        table_rows(table, "Bayes")


def test_uncertainty_check_ranks_queries():
    truth = frames(8)
    # Errors grow with the index; so does the spread: a perfect uncertainty.
    bayes = result("Bayes", truth, 0.1, spreads=np.arange(8.0))
    check = uncertainty_check(bayes, share=0.25)
    assert check["queries_per_group"] == 2
    assert check["most_uncertain_median_position_m"] > check["least_uncertain_median_position_m"]
    assert check["spread_error_rank_correlation"] == pytest.approx(1.0)
    assert uncertainty_check(result("PoseNet", truth, 0.1)) is None


@pytest.fixture
def tiny_results():
    truth = frames(6)
    return [result("PoseNet", truth, 0.3), result("Ours", truth, 0.1, spreads=np.ones(6))]


def assert_png(path):
    assert path.is_file() and path.stat().st_size > 1000
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("kind", ["position", "orientation"])
def test_error_histogram_png(tmp_path, tiny_results, kind):
    assert_png(figures.error_histogram(tiny_results, kind, tmp_path / f"{kind}.png"))


def test_error_curves_png(tmp_path, tiny_results):
    assert_png(figures.error_curves(tiny_results, tmp_path / "curves.png"))


def test_trajectory_png(tmp_path, tiny_results):
    assert_png(figures.trajectory_top_down(frames(10), tiny_results, tmp_path / "traj.png"))


def test_tsne_png(tmp_path):
    rng = np.random.default_rng(0)
    features = rng.normal(size=(20, 8))
    centres = rng.normal(size=(3, 8))
    labels = rng.integers(0, 3, size=20)
    assert_png(figures.tsne_of_map(features, centres, labels, tmp_path / "tsne.png"))


def test_crop_seed_spread_of_the_medians():
    truth = frames(5)
    # Position errors offset * (i + 1) for i = 0..4: the median is 3 * offset.
    by_seed = {
        0: result("GA", truth, 0.1),
        1: result("GA", truth, 0.2),
        2: result("GA", truth, 0.3),
    }
    spread = crop_seed_spread(by_seed)
    assert spread["seeds"] == [0, 1, 2]
    assert np.allclose(spread["median_position_m"], [0.3, 0.6, 0.9])
    position = spread["median_position_m_spread"]
    assert position["mean"] == pytest.approx(0.6)
    assert position["std"] == pytest.approx(0.3)  # sample std of 0.3, 0.6, 0.9
    assert (position["min"], position["max"]) == pytest.approx((0.3, 0.9))
    table = crop_seed_markdown({"room": {"GA": spread}})
    assert "| room | GA | 0 1 2 | 0.600 +- 0.300 (0.300 - 0.900) |" in table
