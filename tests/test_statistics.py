"""Paired statistics on cases with a known answer."""

import numpy as np
import pytest

from relocfw.report.statistics import difference, paired_test, spread, verdict


def test_a_clearly_better_method_is_significantly_lower():
    rng = np.random.default_rng(0)
    reference = rng.exponential(1.0, size=(3, 200))
    better = reference * 0.5  # every query halved, on every seed
    test = paired_test(better, reference, seed=1)
    expected = np.mean(np.median(better, axis=1) - np.median(reference, axis=1))
    assert test["median_difference"] == pytest.approx(expected)
    low, high = test["bootstrap_95"]
    assert low < test["median_difference"] < high < 0
    assert test["wilcoxon_p"] < 1e-6
    assert test["method_better_share"] == 1.0
    assert test["verdict"] == "significantly lower"
    assert paired_test(reference, better, seed=1)["verdict"] == "significantly higher"


def test_noise_around_the_same_errors_is_not_significant():
    rng = np.random.default_rng(0)
    reference = rng.exponential(1.0, size=(3, 300))
    # A symmetric perturbation: the same method, measured again.
    noisy = reference + rng.choice([-0.01, 0.01], size=reference.shape)
    test = paired_test(noisy, reference, seed=2)
    low, high = test["bootstrap_95"]
    assert low < 0 < high
    assert test["wilcoxon_p"] > 0.05
    assert test["verdict"] == "no significant difference"


def test_identical_answers_and_shared_failures_are_ties():
    errors = np.array([[0.1, np.inf, 0.3]])
    test = paired_test(errors, errors.copy())
    assert test["wilcoxon_p"] == 1.0 and test["median_difference"] == 0.0
    assert test["verdict"] == "no significant difference"
    assert difference(np.array([np.inf]), np.array([np.inf]))[0] == 0.0
    assert difference(np.array([np.inf]), np.array([1.0]))[0] == np.inf


def test_the_verdict_needs_both_tests_in_the_same_direction():
    assert verdict(0.001, -0.2, -0.1, direction=-1) == "significantly lower"
    assert verdict(0.001, -0.2, 0.1, direction=-1).startswith("inconclusive")
    assert verdict(0.2, 0.1, 0.2, direction=1).startswith("inconclusive")
    assert verdict(0.2, -0.1, 0.2, direction=1) == "no significant difference"
    # Medians lower, but the signed ranks lean the other way: not a finding.
    assert verdict(0.001, -0.2, -0.1, direction=1).startswith("inconclusive")


def test_a_method_that_fails_every_query_is_significantly_worse():
    rng = np.random.default_rng(0)
    reference = rng.exponential(1.0, size=(2, 50))
    failed = np.full_like(reference, np.inf)
    test = paired_test(failed, reference)
    assert test["bootstrap_95"] == [np.inf, np.inf]
    assert test["median_difference"] == np.inf
    assert test["verdict"] == "significantly higher"
    # Failing a third of the queries moves the median but leaves the interval finite.
    some = reference.copy()
    some[:, ::3] = np.inf
    low, high = paired_test(some, reference)["bootstrap_95"]
    assert np.isfinite(low) and 0 < low <= high


def test_spread_over_seeds():
    s = spread([1.0, 2.0, 3.0])
    assert (s["mean"], s["std"], s["min"], s["max"]) == (2.0, 1.0, 1.0, 3.0)
    assert spread([4.0])["std"] == 0.0


def test_mismatched_pairs_are_refused():
    with pytest.raises(ValueError, match="shape"):
        paired_test(np.zeros((2, 3)), np.zeros((2, 4)))
