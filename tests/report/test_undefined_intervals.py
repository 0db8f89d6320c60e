"""An interval whose bounds are infinite only because undefined resamples fill its
tails reads as undefined, with their count, never as "no significant difference"."""

import numpy as np

from relocfw.report.seed_comparison import seed_comparison, seed_markdown
from relocfw.report.statistics import paired_test, percentile_interval
from tests.report.test_seed_comparison import answered


def opposite_failures() -> tuple[np.ndarray, np.ndarray]:
    """[2, 20] errors where the method fails 9 queries on seed 0 and the reference
    the same 9 on seed 1: each observed median is finite (9 of 20), but a resample
    drawing 10 or more of them has an infinite median on both seeds, +inf - inf."""
    base = np.random.default_rng(0).uniform(0.1, 1.0, size=20)
    errors, reference = np.tile(base, (2, 1)), np.tile(base, (2, 1))
    errors[0, :9] = np.inf
    reference[1, :9] = np.inf
    return errors, reference


def test_a_finite_difference_with_an_undefined_interval_is_not_no_difference():
    test = paired_test(*opposite_failures())
    assert np.isfinite(test["median_difference"])
    undefined = test["undefined_resamples"]
    assert 500 < undefined < 1000  # ~41 %: well past either 2.5 % tail
    assert test["verdict"] == f"interval undefined ({undefined} of 2000 resamples undefined)"


def test_the_printed_table_carries_undefined_and_the_count():
    errors, reference = opposite_failures()
    results = {
        seed: {
            "room": {
                "Ref": answered("Ref", [float(e) for e in reference[seed]]),
                "Other": answered("Other", [float(e) for e in errors[seed]]),
            }
        }
        for seed in (0, 1)
    }
    table = seed_comparison(results, {}, "Ref")
    test = table["room"]["Other"]["vs_reference"]["position_m"]
    markdown = seed_markdown(table, "Ref", [0, 1])
    row = next(line for line in markdown.splitlines() if line.startswith("| room | Other |"))
    expected = f"interval undefined ({test['undefined_resamples']} of 2000 resamples undefined)"
    assert expected in row and "no significant difference" not in row


def test_only_bounds_that_undefined_resamples_make_infinite_are_undefined():
    from relocfw.report.statistics import undefined_bounds  # new: imported here alone

    defined = np.linspace(-1.0, 1.0, 1000)
    few = defined.copy()
    few[::100] = np.nan  # 1 %: inside the 2.5 % tails, the bounds stay numbers
    assert undefined_bounds(few) == (False, False)
    many = defined.copy()
    many[::20] = np.nan  # 5 %: past both tails
    assert undefined_bounds(many) == (True, True)
    failing = np.full(1000, np.inf)  # every resample: the method's median is infinite
    failing[::20] = np.nan
    assert percentile_interval(failing) == (-np.inf, np.inf)
    assert undefined_bounds(failing) == (True, False)  # +inf is the method's failures
