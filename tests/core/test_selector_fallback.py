"""The learned window selector falls back to the centre window, not to any other.

LearnedSelector answers with the window whose predicted error gain over the centre crop
is best, but only where that gain is negative (the model expects the window to beat the
centre); otherwise it answers the centre crop's window. The centre is never the first
or the last window here, nor the one predicted best, so a fall-back to any other window
(the first, the nearest to the map, the best predicted) answers differently.
"""

import numpy as np

from relocfw.core.window_rules import LearnedSelector, Windows
from tests.rotations import axis_angle


class FixedPredictions:
    """A stand-in for the fitted regressor: the same predicted gains for any query."""

    def __init__(self, gains: list[float]) -> None:
        self.gains = np.asarray(gains, dtype=np.float64)

    def predict(self, features: np.ndarray) -> np.ndarray:
        assert len(features) == len(self.gains)
        return self.gains


def random_windows(rng: np.random.Generator, count: int = 5, centre: int = 2) -> Windows:
    """`count` windows with random poses and distances, the centre crop at `centre`."""
    return Windows(
        distances=rng.uniform(0.5, 1.5, count),
        positions=rng.normal(size=(count, 3)),
        quaternions=np.array(
            [axis_angle(rng.normal(size=3), a) for a in rng.uniform(0, 90, count)]
        ),
        offsets=np.linspace(0.0, 1.0, count),
        centre=centre,
    )


def test_no_predicted_gain_answers_the_centre_window():
    windows = random_windows(np.random.default_rng(0))
    # Window 1 is predicted best, but worse than the centre (gain > 0): stay there.
    selector = LearnedSelector(model=FixedPredictions([0.3, 0.1, 0.4, 0.2, 0.6]))
    choice = selector(windows)
    assert choice.window == windows.centre == 2
    assert np.array_equal(choice.position, windows.positions[2])
    # A gain of exactly 0 is no gain either.
    assert LearnedSelector(model=FixedPredictions([0.3, 0.0, 0.4, 0.2, 0.6]))(windows).window == 2
    # A predicted gain leaves the centre for the window that promises it.
    assert LearnedSelector(model=FixedPredictions([0.3, -0.1, 0.4, 0.2, 0.6]))(windows).window == 1


def test_a_selector_trained_where_the_centre_always_wins_answers_the_centre():
    # The centre crop's window has the smallest error on every validation query, at a
    # different place among the windows from query to query; the fitted model's gains
    # for the centre scatter about 0 (it is the reference), so on fresh queries it
    # answers the centre either as the best predicted window or by falling back.
    rng = np.random.default_rng(1)
    queries, errors = [], []
    for _ in range(60):
        windows = random_windows(rng, centre=int(rng.integers(1, 4)))
        queries.append(windows)
        errors.append(np.where(np.arange(5) == windows.centre, 0.1, 2.0 + rng.uniform(size=5)))
    selector = LearnedSelector(seed=0).fit(queries, errors, [f"val-{i}" for i in range(60)])
    fresh = [random_windows(rng, centre=int(rng.integers(1, 4))) for _ in range(20)]
    assert [selector(w).window for w in fresh] == [w.centre for w in fresh]
