"""Paired statistics on cases with a known answer."""

import numpy as np
import pytest
from scipy.stats import wilcoxon

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


def test_failures_on_opposite_seeds_are_undefined_never_no_difference():
    # The same 20 errors for both, but 12 queries fail: the method's on seed 0, the
    # reference's on seed 1. Each side's median is inf on a different seed, so the
    # mean over seeds of the difference of medians is +inf and -inf at once.
    base = np.random.default_rng(0).uniform(0.1, 1.0, size=20)
    errors, reference = np.tile(base, (2, 1)), np.tile(base, (2, 1))
    errors[0, :12] = np.inf
    reference[1, :12] = np.inf
    test = paired_test(errors, reference)
    assert np.isnan(test["median_difference"])
    assert test["verdict"].startswith("undefined")
    # The interval is still defined: undefined resamples could lie anywhere.
    assert test["bootstrap_95"] == [-np.inf, np.inf]
    assert test["undefined_resamples"] > 0
    # Each failed query failed once on each side: ties, as the unfailed ones are.
    assert test["untied_pairs"] == 0 and test["wilcoxon_p"] == 1.0
    reference[1, :12] = np.nan  # a NaN error is a failure too
    again = paired_test(errors, reference)
    assert again["verdict"] == test["verdict"] and again["bootstrap_95"] == test["bootstrap_95"]


def test_an_undefined_p_or_bound_is_never_read_as_no_difference():
    nan = float("nan")
    assert verdict(nan, -0.1, 0.1, direction=0).startswith("undefined")
    assert verdict(0.5, nan, nan, direction=0).startswith("undefined")
    assert verdict(0.001, -0.2, nan, direction=-1).startswith("undefined")


def test_undefined_resamples_widen_the_interval_never_shrink_it():
    from relocfw.report.statistics import percentile_interval

    defined = np.linspace(-1.0, 1.0, 1000)
    few = defined.copy()
    few[::100] = np.nan  # 1%, inside the 2.5% tails: the bounds stay finite
    low, high = percentile_interval(few)
    assert np.isfinite([low, high]).all()
    assert low <= percentile_interval(defined)[0] and high >= percentile_interval(defined)[1]
    many = defined.copy()
    many[::20] = np.nan  # 5%: more than either tail holds
    assert percentile_interval(many) == (-np.inf, np.inf)


def test_the_signed_rank_test_pairs_each_query_within_a_seed():
    # Per query, the method's three seeds hold the reference's errors in another order
    # (x < y < z becomes y, z, x): the median over seeds of each side is the same y,
    # so differencing the medians sees nothing, while on two seeds of three the
    # method's error is higher than the reference's on the same seed.
    rng = np.random.default_rng(0)
    x, y, z = np.sort(rng.uniform(0.1, 1.0, size=(3, 30)), axis=0)
    reference = np.stack([x, y, z])
    errors = np.stack([y, z, x])
    median_of_each = np.median(errors, axis=0) - np.median(reference, axis=0)
    assert np.all(median_of_each == 0)  # the old input: nothing to test
    per_seed_median = np.median(errors - reference, axis=0)  # min(y - x, z - y) > 0
    test = paired_test(errors, reference)
    assert test["untied_pairs"] == 30 and test["method_better_share"] == 0.0
    assert test["wilcoxon_p"] == pytest.approx(wilcoxon(per_seed_median).pvalue)
    assert test["wilcoxon_p"] < 1e-6


def test_two_seeds_with_opposite_failures_on_one_query_tie_on_it():
    from relocfw.report.statistics import per_query_differences

    errors = np.array([[np.inf, 0.2, 0.3], [0.1, 0.2, 0.5]])
    reference = np.array([[0.1, 0.1, 0.3], [np.inf, 0.2, 0.3]])
    # q0: +inf on seed 0, -inf on seed 1, midpoint undefined: a tie. q1: (0.1 + 0)/2.
    differences = per_query_differences(errors, reference)
    assert differences == pytest.approx([0.0, 0.05, 0.1])


def test_a_uniform_five_percent_improvement_is_found_by_the_paired_bootstrap():
    # Errors spread over three orders of magnitude: resampled medians move far more
    # than 5% from one resample to the next, so only resampling the same queries for
    # both methods (the pairing) sees the improvement.
    rng = np.random.default_rng(0)
    reference = 10.0 ** rng.uniform(-2.0, 1.0, size=(3, 200))
    better = 0.95 * reference
    test = paired_test(better, reference, seed=3)
    low, high = test["bootstrap_95"]
    assert low <= test["median_difference"] <= high < 0
    assert test["verdict"] == "significantly lower"


def test_the_signed_rank_direction_is_the_sign_of_the_rank_sum_not_of_the_sign_count():
    from relocfw.report.statistics import signed_rank_direction

    # Three of five differences are positive, but the two negative ones are the
    # largest: signed ranks +1 +2 +3 -4 -5 sum to -3, so the test leans lower.
    differences = np.array([0.1, 0.2, 0.3, -1.0, -2.0])
    assert signed_rank_direction(differences) == -1.0
    assert signed_rank_direction(-differences) == 1.0
    # Ties (zeros) are dropped before ranking, as Wilcoxon drops them.
    assert signed_rank_direction(np.array([0.0, 0.0, 0.1, 0.2, -0.5])) == 0.0


def test_a_method_worse_on_most_queries_by_little_and_far_better_on_the_rest_is_lower():
    # 60 queries 1 cm worse, 40 queries 1 m better: most signs say "higher", the rank
    # sum (the quantity the signed-rank test tests) and the medians say "lower".
    reference = np.tile(np.linspace(2.0, 3.0, 100), (2, 1))
    errors = reference.copy()
    errors[:, :60] += 0.01
    errors[:, 60:] -= 1.0
    test = paired_test(errors, reference, seed=0, resamples=500)
    assert test["method_better_share"] == 0.4
    low, high = test["bootstrap_95"]
    assert high < 0 and test["wilcoxon_p"] < 0.05
    assert test["verdict"] == "significantly lower"


def test_the_bootstrap_resamples_the_same_queries_on_every_seed():
    # Seed 1 holds seed 0's errors with the two methods swapped: on any one set of rows the
    # difference of medians is +d on seed 0 and -d on seed 1, so the mean over seeds
    # is exactly 0 on every resample. Rows drawn apart per seed would not cancel.
    rng = np.random.default_rng(0)
    a, b = rng.exponential(1.0, size=(2, 40))
    errors, reference = np.stack([a, b]), np.stack([b, a])
    test = paired_test(errors, reference, seed=4, resamples=300)
    assert test["median_difference"] == 0.0
    assert test["bootstrap_95"] == [0.0, 0.0]


def test_seeds_with_the_same_errors_give_the_interval_of_one_seed():
    # With the rows shared by every seed, repeating one seed's errors changes no
    # resample: the interval is the one-seed interval from the same bootstrap seed.
    rng = np.random.default_rng(1)
    reference = rng.exponential(1.0, size=(1, 50))
    errors = reference * rng.uniform(0.5, 1.2, size=(1, 50))
    one = paired_test(errors, reference, seed=5, resamples=400)
    repeated = np.repeat(errors, 3, axis=0), np.repeat(reference, 3, axis=0)
    three = paired_test(*repeated, seed=5, resamples=400)
    assert three["bootstrap_95"] == pytest.approx(one["bootstrap_95"], abs=1e-12)
