"""A refiner's confidence feeds the uncertainty measures beside the sampled spreads."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from relocfw.app.tasks.compare import seed_tables
from relocfw.core.values import Crop, Localization, Pose
from relocfw.data.frames import Frame
from relocfw.report import figures
from relocfw.report.comparison import uncertainty_check
from relocfw.report.evaluation import (
    CONFIDENCE_SIGNAL,
    MethodResult,
    per_image_csv,
    spread_source,
    summarise,
    uncertainty_columns,
    uncertainty_quality_of,
    uncertainty_signal_of,
)
from relocfw.report.seed_comparison import UNCERTAINTY_TITLES, seed_comparison, seed_markdown
from relocfw.report.uncertainty import confidence_uncertainty, uncertainty_quality
from relocfw.report.units import METRES

NAN = float("nan")
# Position errors (m along x); orientation errors grow with them (degrees about z).
ERRORS = np.array([0.5, 0.1, 0.9, 0.3, 0.7, 0.2, 0.4, 0.8, 0.6, 1.0])


def result(
    method: str,
    confidence: list[float] | np.ndarray | None = None,
    fell_back: list[bool] | None = None,
    spread: np.ndarray | None = None,
    errors: np.ndarray = ERRORS,
    spread_source: str = "",
) -> MethodResult:
    """Answers whose position error is `errors` and orientation error 10 x as many degrees."""
    n = len(errors)
    truth = Pose(np.zeros(3), [1.0, 0.0, 0.0, 0.0])
    frames = tuple(Frame(f"q{i}", Path(f"q{i}.png"), truth) for i in range(n))
    confidence = [NAN] * n if confidence is None else confidence
    fell_back = [False] * n if fell_back is None else fell_back
    spread = np.full(n, NAN) if spread is None else spread
    answers = []
    for i, error in enumerate(errors):
        half_angle = np.radians(10.0 * error) / 2
        pose = Pose([error, 0.0, 0.0], [np.cos(half_angle), 0.0, 0.0, np.sin(half_angle)])
        answers.append(
            Localization(
                pose,
                Crop(0, 0, 1),
                0.0,
                1,
                0.0,
                position_spread=float(spread[i]),
                orientation_spread_deg=float(spread[i]),
                refine_confidence=float(confidence[i]),
                fell_back=bool(fell_back[i]),
            )
        )
    return MethodResult(method, frames, tuple(answers), spread_source=spread_source)


def test_less_confidence_is_more_uncertainty_and_fallbacks_come_first():
    confidence = np.array([40.0, 12.0, 30.0, 50.0, NAN])
    fell_back = np.array([False, False, True, True, False])
    uncertainty = confidence_uncertainty(confidence, fell_back)
    assert uncertainty[:2].tolist() == [-40.0, -12.0]
    # Both fallbacks above every accepted answer, in their own order (30 before 50).
    assert uncertainty[2] > uncertainty[3] > uncertainty[1]
    assert np.isnan(uncertainty[4])  # no confidence: none measured, the most uncertain
    # Fallbacks already above the accepted answers are left where they are.
    low = confidence_uncertainty(np.array([40.0, 3.0]), np.array([False, True]))
    assert low.tolist() == [-40.0, -3.0]
    # A fallback claiming infinite confidence is ranked as having none.
    odd = confidence_uncertainty(np.array([40.0, np.inf]), np.array([False, True]))
    assert np.isnan(odd[1])


def test_a_confidence_that_anti_ranks_the_errors_is_a_perfect_signal():
    refined = result("refined", confidence=100.0 - 50.0 * ERRORS)  # fewer inliers, worse
    quality = uncertainty_quality_of(refined)
    for kind in ("position", "orientation"):  # one uncertainty ranks both kinds
        assert quality[kind]["spearman_uncertainty_error"] == pytest.approx(1.0)
        assert quality[kind]["ause"] == pytest.approx(0.0)
    columns = summarise(refined)
    assert columns["uncertainty_signal"] == CONFIDENCE_SIGNAL
    assert columns["position_uncertainty_error_spearman"] == pytest.approx(1.0)
    assert columns["orientation_ause_deg"] == pytest.approx(0.0)
    assert columns["median_position_m_rejecting_30%"] == pytest.approx(
        np.median(np.sort(ERRORS)[:7])
    )
    assert "position_spread_error_spearman" not in columns  # no spread was measured
    # The reverse confidence (more inliers on worse answers) is the worst signal.
    backwards = uncertainty_quality_of(result("backwards", confidence=ERRORS))
    assert backwards["position"]["spearman_uncertainty_error"] == pytest.approx(-1.0)
    assert backwards["position"]["ause"] > 0


def test_fallbacks_rank_as_the_most_uncertain():
    # The two worst answers fell back, with more inliers than any accepted answer:
    # ranked by -inliers alone they would be the most trusted.
    worst = np.argsort(ERRORS)[-2:]
    confidence = 100.0 - 50.0 * ERRORS
    confidence[worst] = [150.0, 140.0]  # the larger error, the fewer inliers
    fell_back = np.isin(np.arange(len(ERRORS)), worst)
    refined = result("refined", confidence=confidence, fell_back=fell_back.tolist())
    signal = uncertainty_signal_of(refined)
    assert signal.from_confidence and signal.fell_back.tolist() == fell_back.tolist()
    assert set(np.argsort(-signal.position)[:2]) == set(worst)
    quality = uncertainty_quality_of(refined)["position"]
    assert quality["spearman_uncertainty_error"] == pytest.approx(1.0)
    assert quality["ause"] == pytest.approx(0.0)
    # Rejecting 20 % rejects exactly the two fallbacks.
    kept = np.delete(ERRORS, worst)
    assert quality["median_after_rejecting"]["20%"] == pytest.approx(np.median(kept))
    check = uncertainty_check(refined, share=0.2)
    assert check["uncertainty_signal"] == CONFIDENCE_SIGNAL
    assert check["most_uncertain_median_position_m"] == pytest.approx(np.mean(ERRORS[worst]))


def test_a_method_with_neither_spread_nor_confidence_has_no_uncertainty():
    plain = result("plain")
    assert uncertainty_signal_of(plain) is None
    assert uncertainty_quality_of(plain) is None and uncertainty_check(plain) is None
    summary = summarise(plain)
    assert uncertainty_columns(plain) == {}
    assert not any("spearman" in key or "ause" in key for key in summary)
    assert "uncertainty_signal" not in summary


def test_a_sampled_method_is_measured_by_its_spread_as_before():
    sampled = result("sampled", spread=np.exp(ERRORS), spread_source="MC dropout")
    columns = uncertainty_columns(sampled)
    assert columns["uncertainty_signal"] == "spread (MC dropout)"
    before = uncertainty_quality(
        sampled.position_errors(), sampled.orientation_errors(), np.exp(ERRORS), np.exp(ERRORS)
    )
    assert columns["position_spread_error_spearman"] == before["position"]["spearman_spread_error"]
    assert columns["position_uncertainty_error_spearman"] == pytest.approx(1.0)
    assert columns["position_ause_m"] == before["position"]["ause"] == 0.0
    # A result built by hand does not know its source: the signal is "spread".
    assert uncertainty_signal_of(result("by hand", spread=ERRORS)).name == "spread"


def test_a_refined_and_sampled_method_is_measured_by_its_confidence():
    # The spread ranks the errors backwards, the confidence exactly: the confidence wins.
    both = result("both", confidence=-ERRORS, spread=-ERRORS, spread_source="MC dropout")
    columns = uncertainty_columns(both)
    assert columns["uncertainty_signal"] == CONFIDENCE_SIGNAL
    assert columns["position_uncertainty_error_spearman"] == pytest.approx(1.0)
    assert "position_spread_error_spearman" not in columns


def test_the_spread_source_names_the_samples():
    def relocalizer(crops):
        return SimpleNamespace(options=SimpleNamespace(crop_samples=crops), backbone=None)

    assert spread_source(relocalizer(8)) == "crop samples"
    assert spread_source(relocalizer(0)) == ""
    assert spread_source(object()) == ""  # any object with `localize` may be evaluated


def test_the_seed_table_says_which_signal_each_row_uses():
    results = {
        seed: {
            "room": {
                "Ref": result("Ref", errors=ERRORS + seed),
                "Bayes": result(
                    "Bayes", spread=ERRORS, errors=ERRORS + seed, spread_source="MC dropout"
                ),
                "Refined": result(
                    "Refined", confidence=-ERRORS, errors=ERRORS + seed, fell_back=[False] * 10
                ),
            }
        }
        for seed in (0, 1)
    }
    table = seed_comparison(results, {"room": result("mean training pose", errors=ERRORS)}, "Ref")
    refined = table["room"]["Refined"]["uncertainty"]
    assert refined["signal"] == CONFIDENCE_SIGNAL
    assert refined["position"]["spearman_uncertainty_error"] == pytest.approx([1.0, 1.0])
    assert refined["orientation"]["ause"]["mean"] == pytest.approx(0.0)
    assert table["room"]["Bayes"]["uncertainty"]["signal"] == "spread (MC dropout)"
    assert "uncertainty" not in table["room"]["Ref"]
    assert "uncertainty" not in table["room"]["mean training pose"]
    markdown = seed_markdown(table, "Ref", [0, 1])
    header = markdown.splitlines()[0]
    assert all(title in header for title in UNCERTAINTY_TITLES)
    row = next(line for line in markdown.splitlines() if line.startswith("| room | Refined |"))
    assert f"| {CONFIDENCE_SIGNAL} | +1.00/+1.00 | +1.00/+1.00 | 0.000 | 0.00 |" in row
    plain = next(line for line in markdown.splitlines() if line.startswith("| room | Ref |"))
    assert plain.endswith("| - | - | - | - | - | - | - |")
    assert "fallbacks the most uncertain" in markdown  # the footnote says how to read it
    # task=compare writes the table through its own unit-aware writer: the same footnote.
    written, _ = seed_tables(table, "Ref", [0, 1], METRES)
    assert "fallbacks the most uncertain" in written
    # Without any signal the table keeps its earlier columns and footnote.
    unmeasured = seed_markdown(
        seed_comparison({0: {"room": {"Ref": result("Ref")}}}, {}, "Ref"), "Ref", [0]
    )
    assert "uncertainty signal" not in unmeasured and "AUSE" not in unmeasured


def test_the_figure_plots_minus_confidence_and_marks_fallbacks(monkeypatch, tmp_path):
    texts: list[str] = []

    def save(figure, path):
        for axis in figure.axes:
            texts.extend([axis.get_xlabel(), axis.get_title()])
            legend = axis.get_legend()
            if legend is not None:
                texts.extend(t.get_text() for t in legend.get_texts())
        texts.extend(t.get_text() for t in figure.texts)
        return Path(path)

    monkeypatch.setattr(figures, "save", save)
    fell_back = [False] * 9 + [True]
    refined = result("Refined", confidence=100.0 - 50.0 * ERRORS, fell_back=fell_back)
    figures.uncertainty_against_error(refined, uncertainty_quality_of(refined), tmp_path / "u.png")
    text = "\n".join(texts)
    assert "-confidence (the refiner's unit, e.g. -PnP inliers)" in text
    assert "fell back (ranked most uncertain)" in text and "by -confidence" in text
    assert f"Refined: {CONFIDENCE_SIGNAL} against error" in text
    assert "spread" not in text


def test_the_per_query_csv_carries_the_confidence_and_the_fallback():
    refined = result("Refined", confidence=[7.0] + [30.0] * 9, fell_back=[True] + [False] * 9)
    rows = list(csv.DictReader(io.StringIO(per_image_csv([refined]))))
    assert rows[0]["refine_confidence"] == "7" and rows[0]["fell_back"] == "1"
    assert rows[1]["fell_back"] == "0"


def test_the_uncertainty_columns_name_no_metres_for_a_non_metric_run():
    from relocfw.report.seed_comparison import seed_rows
    from relocfw.report.units import model_units, relabel_row, relabel_table, relabel_tree

    unit = model_units()
    refined = result("Refined", confidence=-ERRORS)
    assert "position_ause_units" in relabel_row(summarise(refined), unit)
    table = seed_comparison({0: {"room": {"Ref": result("Ref"), "Refined": refined}}}, {}, "Ref")
    header, _ = relabel_table(*seed_rows(table, "Ref"), unit)
    assert "AUSE pos (model units)" in header and not any("(m)" in title for title in header)
    stats = relabel_tree(table["room"]["Refined"]["uncertainty"], unit)
    assert stats == table["room"]["Refined"]["uncertainty"]  # no key names metres


def test_the_uncertainty_check_ranks_a_missing_confidence_as_most_uncertain():
    # The largest error has no confidence: ranked most uncertain, the ranking stays
    # perfect (a NaN passed to Spearman would make the whole correlation NaN).
    confidence = -ERRORS.copy()
    confidence[np.argmax(ERRORS)] = NAN
    check = uncertainty_check(result("Refined", confidence=confidence))
    assert check["spread_error_rank_correlation"] == pytest.approx(1.0)
