"""Uncertainty quality on constructed cases: sparsification, AUSE, rejection medians."""

import numpy as np
import pytest

from relocfw.report.uncertainty import (
    ause,
    rejection_medians,
    sparsification_curve,
    uncertainty_quality,
)

ERRORS = np.array([0.5, 0.1, 0.9, 0.3, 0.7, 0.2, 0.4, 0.8, 0.6, 1.0])


def test_the_sparsification_curve_removes_the_most_uncertain_first():
    order = np.argsort(-ERRORS)  # largest error first: the oracle
    curve = sparsification_curve(ERRORS, order)
    assert curve[0] == pytest.approx(np.median(ERRORS))
    assert curve[1] == pytest.approx(np.median(np.sort(ERRORS)[:9]))  # 1.0 removed
    assert curve[-1] == pytest.approx(0.1)  # only the smallest error left
    assert np.all(np.diff(curve) <= 0)


def test_uncertainty_equal_to_error_gives_ause_zero():
    assert ause(ERRORS, ERRORS)["ause"] == 0.0
    # Any increasing function of the error ranks the same: still zero.
    assert ause(ERRORS, np.exp(3 * ERRORS))["ause"] == 0.0


def test_reversed_uncertainty_gives_the_largest_ause():
    reversed_area = ause(ERRORS, -ERRORS)["ause"]
    # By hand: removing the smallest errors first keeps the largest ones.
    kept_largest = [np.median(np.sort(ERRORS)[i:]) for i in range(10)]
    kept_smallest = [np.median(np.sort(ERRORS)[: 10 - i]) for i in range(10)]
    assert reversed_area == pytest.approx(np.mean(np.subtract(kept_largest, kept_smallest)))
    rng = np.random.default_rng(0)
    for _ in range(200):
        assert ause(ERRORS, rng.permutation(ERRORS))["ause"] <= reversed_area + 1e-12


def test_median_after_rejecting_the_most_uncertain():
    # The spread flags the three worst answers exactly, then ranks the rest in reverse.
    spread = np.array([4, 9, 20, 6, 18, 8, 5, 19, 3, 21], dtype=float)
    medians = rejection_medians(ERRORS, spread)
    # 10%: drops 1.0; 20%: also 0.9; 30%: also 0.8 (the three largest spreads).
    assert medians["10%"] == pytest.approx(np.median([0.5, 0.1, 0.9, 0.3, 0.7, 0.2, 0.4, 0.8, 0.6]))
    assert medians["20%"] == pytest.approx(np.median([0.5, 0.1, 0.3, 0.7, 0.2, 0.4, 0.8, 0.6]))
    assert medians["30%"] == pytest.approx(np.median([0.5, 0.1, 0.3, 0.7, 0.2, 0.4, 0.6]))


def test_quality_of_both_spreads_and_none_when_not_sampled():
    quality = uncertainty_quality(ERRORS, ERRORS * 10, ERRORS, -ERRORS)
    assert quality["position"]["spearman_spread_error"] == pytest.approx(1.0)
    assert quality["position"]["ause"] == 0.0
    assert quality["orientation"]["spearman_spread_error"] == pytest.approx(-1.0)
    assert quality["orientation"]["ause"] > 0
    nan = np.full(10, np.nan)
    assert uncertainty_quality(ERRORS, ERRORS, nan, nan) is None


def test_a_sampled_methods_summary_carries_its_uncertainty_columns():
    from pathlib import Path

    from relocfw.app.results import summary_csv
    from relocfw.core.values import Crop, Localization, Pose
    from relocfw.data.frames import Frame
    from relocfw.report.evaluation import MethodResult, summarise

    identity = np.array([1.0, 0.0, 0.0, 0.0])
    truth = Pose(np.zeros(3), identity)
    frames = tuple(Frame(f"q{i}", Path(f"q{i}.png"), truth) for i in range(len(ERRORS)))

    def answers(spreads):
        return tuple(
            Localization(
                Pose([e, 0.0, 0.0], identity),
                Crop(0, 0, 1),
                0.0,
                1,
                0.0,
                position_spread=s,
                orientation_spread_deg=s,
            )
            for e, s in zip(ERRORS, spreads, strict=True)
        )

    sampled = summarise(MethodResult("sampled", frames, answers(ERRORS)))
    assert sampled["position_spread_error_spearman"] == pytest.approx(1.0)
    assert sampled["position_ause_m"] == 0.0
    assert sampled["median_position_m_rejecting_30%"] == pytest.approx(
        np.median(np.sort(ERRORS)[:7])
    )
    plain = summarise(MethodResult("plain", frames, answers([float("nan")] * len(ERRORS))))
    assert "position_ause_m" not in plain
    header = summary_csv([plain, sampled]).splitlines()[0]
    assert header.endswith("median_orientation_deg_rejecting_30%")


TWENTY = np.linspace(0.05, 1.0, 20)


def test_one_failed_query_among_twenty_leaves_ause_finite_and_counted():
    errors = TWENTY.copy()
    errors[7] = np.inf
    spread = TWENTY.copy()
    spread[7] = 0.0  # the spread misses the failure: it keeps it to the end
    curves = ause(errors, spread)
    answered = np.arange(20) != 7
    assert curves["ause"] == pytest.approx(ause(TWENTY[answered], spread[answered])["ause"])
    assert curves["failed_queries"] == 1 and len(curves["oracle"]) == 19
    errors[7] = np.nan  # a NaN error is a failure too
    assert ause(errors, spread)["ause"] == curves["ause"]
    # Nothing answered: no area to measure, said as NaN, not as 0 or inf.
    nothing = ause(np.full(4, np.inf), np.arange(4.0))
    assert np.isnan(nothing["ause"]) and nothing["failed_queries"] == 4


def test_the_sparsification_curve_counts_a_failure_as_infinite_never_nan():
    errors = ERRORS.copy()
    errors[1] = np.nan  # the 0.1 query failed
    order = np.argsort(-ERRORS)  # ranked as if it had been the best: removed last
    curve = sparsification_curve(errors, order)
    assert not np.isnan(curve).any()
    # Inf once the failure fills half of what is kept: the last two entries.
    assert np.isinf(curve[-2:]).all() and np.isfinite(curve[:-2]).all()
    assert curve[0] == pytest.approx(np.median(np.where(np.isnan(errors), np.inf, errors)))


def test_a_query_without_a_spread_is_the_most_uncertain_everywhere():
    spread = ERRORS.copy()
    spread[9] = np.nan  # the largest error (1.0) has no spread
    medians = rejection_medians(ERRORS, spread)
    assert medians["10%"] == pytest.approx(np.median(np.delete(ERRORS, 9)))  # 1.0 rejected
    assert ause(ERRORS, spread)["ause"] == 0.0  # ranked exactly as its error is
    quality = uncertainty_quality(ERRORS, ERRORS, spread, spread)
    assert quality["position"]["spearman_spread_error"] == pytest.approx(1.0)
    assert quality["position"]["ause"] == 0.0


def test_a_failed_query_is_infinitely_wrong_in_spearman_and_the_rejection_medians():
    errors = ERRORS.copy()
    errors[0] = np.inf
    spread = ERRORS.copy()
    spread[0] = 10.0  # the spread flags the failure as the most uncertain
    quality = uncertainty_quality(errors, errors, spread, spread)["position"]
    assert quality["spearman_spread_error"] == pytest.approx(1.0)  # the failure ranks last
    assert quality["failed_queries"] == 1
    assert np.isfinite(quality["ause"])
    # 10% rejects the failure; kept, as when the spread is low, it counts as inf.
    assert quality["median_after_rejecting"]["10%"] == pytest.approx(np.median(ERRORS[1:]))
    spread[0] = 0.0
    kept = rejection_medians(errors, spread)["10%"]
    assert kept == pytest.approx(np.median(np.delete(errors, 9)))  # 1.0 rejected, inf kept
    assert kept > np.median(np.delete(ERRORS, [0, 9]))
