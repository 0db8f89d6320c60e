"""Calibrated error bounds (relocfw.core.error_bounds): split conformal per signal bin."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from relocfw.core.error_bounds import SIGNALS, BinnedBound, ErrorBounds, calibrate
from relocfw.core.errors import ConfigError, DataError

NAN = float("nan")


def heteroscedastic(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Signals in (0, 1) and errors whose spread grows as the signal falls."""
    signal = rng.uniform(0, 1, count)
    errors = np.abs(rng.normal(0, 0.05 + (1 - signal), count))
    return errors, signal


def test_coverage_holds_on_fresh_draws_and_is_not_loose():
    rng = np.random.default_rng(7)
    coverages, least_trusted = [], []
    for _ in range(400):
        errors, signal = heteroscedastic(rng, 60)
        bound = calibrate(errors, signal, np.zeros(60, dtype=bool), coverage=0.9, bins=3)
        assert len(bound.bounds) == 3  # 60 answers at 0.9: three bins of 20
        test_errors, test_signal = heteroscedastic(rng, 500)
        limits = bound.bounds_of(test_signal, np.zeros(500, dtype=bool))
        covered = test_errors <= limits
        coverages.append(covered.mean())
        # Mondrian: the guarantee holds within each bin, the least trusted included.
        in_first = test_signal < bound.edges[0]
        least_trusted.append(covered[in_first].mean())
    # Each bin's bound is the 19th of 20 errors: expected coverage 19/21 = 0.905.
    # With the n-th instead of the (n+1)-th quantile rule it would be 18/21 = 0.857.
    assert np.mean(coverages) >= 0.9 - 0.01
    assert np.mean(coverages) <= 0.9 + 0.08
    assert np.mean(least_trusted) >= 0.9 - 0.015


def test_coverage_holds_with_fallbacks_in_the_mix():
    rng = np.random.default_rng(11)
    coverages = []
    for _ in range(300):
        errors, signal = heteroscedastic(rng, 100)
        fell_back = rng.uniform(size=100) < 0.3
        errors = np.where(fell_back, errors * 5, errors)
        bound = calibrate(errors, signal, fell_back)
        test_errors, test_signal = heteroscedastic(rng, 400)
        test_fell_back = rng.uniform(size=400) < 0.3
        test_errors = np.where(test_fell_back, test_errors * 5, test_errors)
        covered = test_errors <= bound.bounds_of(test_signal, test_fell_back)
        coverages.append(covered[test_fell_back].mean())
    assert np.mean(coverages) >= 0.9 - 0.015


def test_bounds_fall_as_the_signal_rises():
    rng = np.random.default_rng(3)
    errors, signal = heteroscedastic(rng, 600)
    bound = calibrate(errors, signal, np.zeros(600, dtype=bool), coverage=0.9, bins=3)
    assert bound.counts.tolist() == [200, 200, 200]
    np.testing.assert_allclose(bound.edges, [1 / 3, 2 / 3], atol=0.06)
    # Adaptive, not one bound for all: each more trusted bin is clearly tighter.
    assert bound.bounds[0] > 1.3 * bound.bounds[1] > 1.3**2 * bound.bounds[2]
    assert bound.bound(0.95, False) == bound.bounds[2]
    assert bound.bound(0.05, False) == bound.bounds[0]


def test_the_finite_sample_rule_on_a_hand_example():
    nine = np.array([5.0, 1, 9, 3, 7, 2, 8, 4, 6])
    signal = np.linspace(0, 1, 9)
    trusted = np.zeros(9, dtype=bool)
    # ceil((9 + 1) * 0.9) = 9: the 9th smallest of 9.
    assert calibrate(nine, signal, trusted, coverage=0.9).bounds.tolist() == [9.0]
    # ceil((8 + 1) * 0.9) = 9 > 8: too few answers for a finite bound.
    assert calibrate(nine[:8], signal[:8], trusted[:8], coverage=0.9).bounds.tolist() == [math.inf]
    # ceil(10 * 0.5) = 5: the 5th smallest.
    assert calibrate(nine, signal, trusted, coverage=0.5).bounds.tolist() == [5.0]
    # A failed answer (+inf error) counts as the largest.
    failed = np.where(nine == 9, math.inf, nine)
    assert calibrate(failed, signal, trusted).bounds.tolist() == [math.inf]
    assert calibrate(failed, signal, trusted, coverage=0.8).bounds.tolist() == [8.0]


def test_a_bin_too_small_for_the_coverage_is_not_made():
    rng = np.random.default_rng(0)
    errors, signal = heteroscedastic(rng, 59)
    trusted = np.zeros(59, dtype=bool)
    assert len(calibrate(errors, signal, trusted, bins=3).bounds) == 2  # 59 // 20
    # At 0.99 a bin needs 99 answers for a finite bound.
    errors, signal = heteroscedastic(rng, 300)
    bound = calibrate(errors, signal, np.zeros(300, dtype=bool), coverage=0.99, bins=5)
    assert len(bound.bounds) == 3
    assert np.isfinite(bound.bounds).all()


def test_monotone_repair_raises_a_less_trusted_bin():
    signal = np.arange(60.0)
    spread = np.arange(20) / 100
    # The middle bin has the smallest errors, the most trusted bin middling ones.
    errors = np.concatenate([1.0 + spread, 0.1 + spread, 0.5 + spread])
    bound = calibrate(errors, signal, np.zeros(60, dtype=bool), coverage=0.9, bins=3)
    np.testing.assert_allclose(bound.edges, [19.5, 39.5])
    # Raw 19th smallest of each bin: 1.18, 0.28, 0.68; the middle one rises to 0.68.
    np.testing.assert_allclose(bound.bounds, [1.18, 0.68, 0.68])


def test_ties_go_to_the_more_trusted_bin_in_calibration_and_lookup():
    rng = np.random.default_rng(5)
    # A saturated confidence: 40 answers at exactly 1.0 cannot be split.
    signal = np.concatenate([rng.uniform(0, 0.9, 20), np.ones(40)])
    errors = rng.uniform(0, 1, 60)
    trusted = np.zeros(60, dtype=bool)
    bound = calibrate(errors, signal, trusted, bins=3)
    assert bound.counts.tolist() == [20, 40]
    # Every bin's bound is the conformal bound of exactly the answers lookup puts there.
    groups = np.searchsorted(bound.edges, signal, side="right")
    for b, limit in enumerate(bound.bounds):
        mine = np.sort(errors[groups == b])
        assert len(mine) == bound.counts[b]
        assert limit >= mine[math.ceil((len(mine) + 1) * 0.9) - 1]
    edge_case = calibrate(errors, np.arange(60.0), trusted, bins=3)
    assert edge_case.bound(edge_case.edges[0], False) == edge_case.bounds[1]


def test_untrusted_answers_form_their_own_group():
    rng = np.random.default_rng(2)
    errors, signal = heteroscedastic(rng, 80)
    fell_back = np.zeros(80, dtype=bool)
    fell_back[:9] = True
    errors[:9] = np.arange(100.0, 109.0)
    signal[9:12] = NAN  # no signal, did not fall back: untrusted too (two bins here)
    errors[9:12] = 1000.0
    bound = calibrate(errors, signal, fell_back)
    assert bound.untrusted_count == 12
    assert bound.counts.sum() == 68 and len(bound.bounds) == 3
    # 12 answers: the ceil(13 * 0.9) = 12th smallest, a NaN-signal one.
    assert bound.untrusted_bound == 1000.0
    assert bound.bound(0.99, True) == 1000.0
    assert bound.bound(NAN, False) == 1000.0
    assert np.isfinite(bound.bounds).all() and bound.bounds.max() < 100
    # Too few untrusted answers, or none at all: an honest inf.
    assert calibrate(errors[5:], signal[5:], fell_back[5:]).untrusted_bound == math.inf
    assert calibrate(errors[12:], signal[12:], fell_back[12:]).untrusted_bound == math.inf
    assert calibrate(errors[12:], signal[12:], fell_back[12:]).untrusted_count == 0


def test_signal_none_bounds_every_answer_by_the_marginal_group():
    rng = np.random.default_rng(4)
    errors = rng.uniform(0, 1, 60)
    no_signal = np.full(60, NAN)
    bound = calibrate(errors, no_signal, np.zeros(60, dtype=bool), bins=3)
    marginal = np.sort(errors)[math.ceil(61 * 0.9) - 1]
    assert bound.bounds.tolist() == [marginal] and bound.counts.tolist() == [60]
    assert bound.untrusted_count == 0 and bound.untrusted_bound == math.inf
    assert bound.bound(NAN, False) == marginal
    assert bound.bound(NAN, True) == math.inf
    # Answers that fell back keep their own group.
    fell_back = np.arange(60) < 10
    mixed = calibrate(errors + 10 * fell_back, no_signal, fell_back)
    assert mixed.counts.tolist() == [50] and mixed.untrusted_count == 10
    assert mixed.bound(NAN, False) == np.sort(errors[10:])[math.ceil(51 * 0.9) - 1]
    assert mixed.bound(NAN, True) == np.sort(errors[:10] + 10)[-1]


def test_vectorised_bounds_equal_the_scalar_bound():
    rng = np.random.default_rng(9)
    errors, signal = heteroscedastic(rng, 200)
    fell_back = rng.uniform(size=200) < 0.2
    bound = calibrate(errors, signal, fell_back)
    queries = np.concatenate([rng.uniform(-0.5, 1.5, 50), bound.edges, [NAN, math.inf]])
    flags = rng.uniform(size=len(queries)) < 0.3
    vectorised = bound.bounds_of(queries, flags)
    scalar = [bound.bound(float(s), bool(f)) for s, f in zip(queries, flags, strict=True)]
    assert vectorised.tolist() == scalar
    assert len(set(scalar)) >= 3  # the queries reach several groups


def make_bounds() -> ErrorBounds:
    rng = np.random.default_rng(1)
    errors, signal = heteroscedastic(rng, 90)
    fell_back = rng.uniform(size=90) < 0.2
    errors[0] = math.inf
    return ErrorBounds(
        coverage=0.9,
        signal="refiner confidence",
        position=calibrate(errors, signal, fell_back),
        orientation=calibrate(errors * 30, signal, fell_back, bins=2),
        validation_size=90,
    )


def same_binned(a: BinnedBound, b: BinnedBound) -> bool:
    return (
        np.array_equal(a.edges, b.edges)
        and np.array_equal(a.bounds, b.bounds)
        and np.array_equal(a.counts, b.counts)
        and a.counts.dtype == b.counts.dtype == np.int64
        and a.untrusted_bound == b.untrusted_bound
        and a.untrusted_count == b.untrusted_count
    )


def test_state_round_trip_is_exact():
    bounds = make_bounds()
    state = bounds.state()
    assert all(k.startswith("bounds.") for k in state)
    assert all(isinstance(v, torch.Tensor) for v in state.values())
    loaded = ErrorBounds.from_state({**state, "other.weight": torch.zeros(2)}, "model.pt")
    assert loaded.coverage == 0.9 and loaded.signal == "refiner confidence"
    assert loaded.validation_size == 90
    assert same_binned(loaded.position, bounds.position)
    assert same_binned(loaded.orientation, bounds.orientation)
    assert len(loaded.orientation.bounds) == 2
    for signal in SIGNALS:
        again = ErrorBounds(0.8, signal, bounds.position, bounds.orientation, 90)
        assert ErrorBounds.from_state(again.state(), "x").signal == signal


def test_state_arrays_do_not_alias_the_bounds():
    bounds = make_bounds()
    state = bounds.state()
    state["bounds.position.bounds"][0] = 123.0
    assert bounds.position.bounds[0] != 123.0
    with pytest.raises(ValueError):
        bounds.position.bounds[0] = 1.0  # read-only


FORGERIES = {
    "NaN bound": ("bounds.position.bounds", lambda s: s.clone().fill_(NAN)),
    "negative bound": ("bounds.orientation.bounds", lambda s: -s.clone()),
    "rising bounds": (
        "bounds.position.bounds",
        lambda s: torch.arange(len(s), dtype=torch.float64),
    ),
    "float32 bounds": ("bounds.position.bounds", lambda s: s.float()),
    "float counts": ("bounds.orientation.counts", lambda s: s.double()),
    "bounds of another shape": ("bounds.position.bounds", lambda s: s.reshape(1, -1)),
    "too many bins": ("bounds.position.bounds", lambda s: torch.zeros(1001, dtype=torch.float64)),
    "no bins": ("bounds.position.bounds", lambda s: torch.zeros(0, dtype=torch.float64)),
    "an edge too many": ("bounds.position.edges", lambda s: torch.cat([s, s[-1:] + 1])),
    "counts of another length": ("bounds.position.counts", lambda s: s[:-1]),
    "decreasing edges": ("bounds.position.edges", lambda s: s.flip(0)),
    "infinite edge": ("bounds.position.edges", lambda s: s.clone().fill_(math.inf)),
    "coverage 1.5": ("bounds.coverage", lambda s: torch.tensor(1.5, dtype=torch.float64)),
    "coverage as a vector": ("bounds.coverage", lambda s: s.reshape(1)),
    "signal code out of range": ("bounds.signal", lambda s: torch.tensor(3)),
    "negative count": ("bounds.position.counts", lambda s: s - 1000),
    "counts that miss answers": ("bounds.orientation.counts", lambda s: s + 1),
    "NaN untrusted bound": (
        "bounds.position.untrusted_bound",
        lambda s: torch.tensor(NAN, dtype=torch.float64),
    ),
    "not a tensor": ("bounds.validation_size", lambda s: 90),
}


@pytest.mark.parametrize("fault", sorted(FORGERIES))
def test_a_forged_state_is_one_data_error_naming_the_key(fault):
    key, change = FORGERIES[fault]
    state = make_bounds().state()
    state[key] = change(state[key])
    with pytest.raises(DataError, match=rf"^model\.pt: {key.replace('.', '[.]')}\b"):
        ErrorBounds.from_state(state, "model.pt")


@pytest.mark.parametrize("key", sorted(make_bounds().state()))
def test_a_missing_key_is_one_data_error_naming_it(key):
    state = make_bounds().state()
    del state[key]
    with pytest.raises(DataError, match=rf"^model\.pt: {key.replace('.', '[.]')}\b"):
        ErrorBounds.from_state(state, "model.pt")


@pytest.mark.parametrize(
    ("options", "key"),
    [
        ({"coverage": 1.5}, "calibrate.coverage"),
        ({"coverage": 1.0}, "calibrate.coverage"),
        ({"coverage": 0.0}, "calibrate.coverage"),
        ({"coverage": NAN}, "calibrate.coverage"),
        ({"coverage": "0.9"}, "calibrate.coverage"),
        ({"bins": 0}, "calibrate.bins"),
        ({"bins": 2.5}, "calibrate.bins"),
    ],
)
def test_impossible_options_are_config_errors_naming_the_option(options, key):
    errors = np.ones(30)
    with pytest.raises(ConfigError, match=key):
        calibrate(errors, np.zeros(30), np.zeros(30, dtype=bool), **options)


@pytest.mark.parametrize(
    ("errors", "signal", "untrusted", "words"),
    [
        (np.ones(5), np.zeros(4), np.zeros(5, dtype=bool), "5 errors, 4 signals"),
        (np.ones(5), np.zeros(5), np.zeros(6, dtype=bool), "6 fell-back flags"),
        (np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool), "no validation answers"),
        (np.array([1.0, NAN]), np.zeros(2), np.zeros(2, dtype=bool), "NaN"),
        (np.array([1.0, -1.0]), np.zeros(2), np.zeros(2, dtype=bool), ">= 0"),
    ],
)
def test_bad_validation_answers_are_data_errors(errors, signal, untrusted, words):
    with pytest.raises(DataError, match=words):
        calibrate(errors, signal, untrusted)


def test_describe_is_one_line_with_the_span_of_bounds():
    line = make_bounds().describe()
    assert "\n" not in line
    assert line.startswith("90% bounds from 90 validation queries (refiner confidence, 3 bins)")
    position = make_bounds().position
    low, high = f"{position.bounds[-1]:.3g}", f"{position.bounds[0]:.3g}"
    assert f"position {low}-{high} m" in line
    assert "fell back or no signal" in line


# --- bounds that their answers cannot support -------------------------------------


def one_answer_bounds(bound: float, coverage: float = 0.99, untrusted: bool = False) -> dict:
    """A state claiming `bound` from a single validation answer (in the one bin, or in
    the untrusted group)."""
    one = BinnedBound(
        edges=np.zeros(0),
        bounds=np.array([math.inf if untrusted else bound]),
        counts=np.array([0 if untrusted else 1]),
        untrusted_bound=bound if untrusted else math.inf,
        untrusted_count=1 if untrusted else 0,
    )
    return ErrorBounds(coverage, "none", one, one, validation_size=1).state()


@pytest.mark.parametrize(
    ("untrusted", "key"),
    [(False, "bounds.position.bounds"), (True, "bounds.position.untrusted_bound")],
    ids=["bin", "untrusted_group"],
)
def test_a_finite_bound_from_too_few_answers_is_refused_naming_the_key(untrusted, key):
    # One answer cannot bound a new one at 99%: calibration gives inf (rank 2 of 1).
    state = one_answer_bounds(0.001, untrusted=untrusted)
    with pytest.raises(DataError, match=rf"^model\.pt: {key.replace('.', '[.]')}\b.*1 answer"):
        ErrorBounds.from_state(state, "model.pt")
    # inf is what calibration gives there, and it loads.
    honest = ErrorBounds.from_state(one_answer_bounds(math.inf, untrusted=untrusted), "model.pt")
    assert honest.position.bound(NAN, untrusted) == math.inf


def test_every_calibrated_bound_passes_the_rank_check():
    rng = np.random.default_rng(3)
    for coverage in (0.5, 0.8, 0.9, 0.95):
        errors, signal = heteroscedastic(rng, 70)
        fell_back = rng.uniform(size=70) < 0.3
        binned = calibrate(errors, signal, fell_back, coverage=coverage, bins=3)
        state = ErrorBounds(coverage, "spread", binned, binned, 70).state()
        assert same_binned(ErrorBounds.from_state(state, "m").position, binned)


@pytest.mark.parametrize("coverage", [1e-12, 0.2, 0.9999999])
def test_a_coverage_outside_the_sane_range_is_refused_by_calibration(coverage):
    with pytest.raises(ConfigError, match="calibrate.coverage"):
        calibrate(np.ones(30), np.zeros(30), np.zeros(30, dtype=bool), coverage=coverage)


@pytest.mark.parametrize("coverage", [0.0, 1.0, 1.5, -0.1])
def test_a_stored_coverage_outside_0_1_is_refused(coverage):
    state = make_bounds().state()
    state["bounds.coverage"] = torch.tensor(coverage, dtype=torch.float64)
    with pytest.raises(DataError, match=r"^model\.pt: bounds[.]coverage must be"):
        ErrorBounds.from_state(state, "model.pt")


def test_a_file_calibrated_at_a_coverage_calibration_now_refuses_still_loads():
    # An older relocfw calibrated at any coverage in (0, 1): such a file loads, and
    # its finite bounds are still held to the answers behind them.
    honest = ErrorBounds.from_state(one_answer_bounds(math.inf, coverage=0.9995), "model.pt")
    assert honest.coverage == 0.9995
    with pytest.raises(DataError, match=r"needs at least 1999"):
        ErrorBounds.from_state(one_answer_bounds(0.001, coverage=0.9995), "model.pt")
