"""The field's metrics on constructed errors: recall bands, the paper's shares, failures."""

import numpy as np
import pytest

from relocfw.report.metrics import RECALL_BANDS, accuracy_metrics, band_key, band_title

# Per query (m, deg), chosen so each band holds a different set of queries:
POSITIONS = np.array([0.01, 0.04, 0.2, 0.3, 0.45, 1.5, 6.0, 0.05])
ORIENTATIONS = np.array([1.0, 4.0, 1.5, 3.0, 4.9, 9.0, 2.0, 1.0])
# 5cm/5deg: q0, q1 (q7 sits on the 5 cm line: strict).  25cm/2deg: q0, q2 (q1 is 4 deg;
# q7 at 5 cm and 1 deg is inside).  50cm/5deg: q0-q4, q7.  5m/10deg: all but q6 (6 m).
EXPECTED_BANDS = {(0.05, 5.0): 2 / 8, (0.25, 2.0): 3 / 8, (0.5, 5.0): 6 / 8, (5.0, 10.0): 7 / 8}


def test_recall_bands_count_queries_within_both_limits():
    metrics = accuracy_metrics(POSITIONS, ORIENTATIONS)
    assert set(EXPECTED_BANDS) == set(RECALL_BANDS)
    for (metres, degrees), share in EXPECTED_BANDS.items():
        assert metrics[band_key(metres, degrees)] == pytest.approx(share), (metres, degrees)
    assert band_key(0.25, 2.0) == "within_0.25m_2deg" and band_title(0.25, 2.0) == "25cm/2deg"
    assert band_title(5.0, 10.0) == "5m/10deg"


def test_the_papers_shares():
    positions = np.array([0.1, 0.5, 0.9, 1.0, 1.2])
    orientations = np.array([10.0, 15.0, 16.0, 20.0, 25.0])
    metrics = accuracy_metrics(positions, orientations)
    assert metrics["share_position_below_0.5m"] == pytest.approx(1 / 5)  # 0.5 is not below
    assert metrics["share_orientation_below_15deg"] == pytest.approx(1 / 5)
    assert metrics["share_position_above_1m"] == pytest.approx(1 / 5)  # 1.0 is not above
    assert metrics["share_orientation_above_20deg"] == pytest.approx(1 / 5)
    assert metrics["share_within_0.5m_15deg"] == pytest.approx(1 / 5)


def test_a_failed_query_counts_as_infinitely_wrong_not_dropped():
    positions = np.array([0.1, 0.2, np.nan, 0.3])
    orientations = np.array([1.0, 1.0, 1.0, np.nan])  # q3 lost only its rotation
    metrics = accuracy_metrics(positions, orientations)
    assert metrics["failed_queries"] == 2
    # Dropping the failures would give a median of 0.15 m, a mean of 0.15 m and
    # 100% within 25cm/2deg; counted as inf they pull all three.
    assert metrics["median_position_m"] == np.inf  # two of four are inf
    assert metrics["mean_position_m"] == np.inf
    assert metrics[band_key(0.25, 2.0)] == pytest.approx(2 / 4)
    assert metrics["share_position_above_1m"] == pytest.approx(2 / 4)
    finite = accuracy_metrics(np.array([0.1, 0.2, np.nan]), np.array([1.0, 1.0, 1.0]))
    assert finite["median_position_m"] == pytest.approx(0.2)  # the failure ranks last


def test_unequal_inputs_are_refused():
    with pytest.raises(ValueError, match="equal"):
        accuracy_metrics(np.zeros(3), np.zeros(2))


@pytest.mark.parametrize(("metres", "degrees"), RECALL_BANDS)
def test_a_query_exactly_on_a_band_limit_is_outside_it(metres, degrees):
    # Strict on both limits (error < limit), as hloc's evaluation counts: q0 sits on
    # the degree limit, q1 on the metre limit, q2 and q3 just inside each.
    positions = np.array([metres / 2, metres, np.nextafter(metres, 0), metres / 2])
    orientations = np.array([degrees, degrees / 2, degrees / 2, np.nextafter(degrees, 0)])
    metrics = accuracy_metrics(positions, orientations)
    assert metrics[band_key(metres, degrees)] == pytest.approx(2 / 4)
