"""The pipeline reads top-down: `localize` is short and names its stages."""

from __future__ import annotations

import inspect

from relocfw import Relocalizer


def test_localize_fits_on_one_screen_and_shows_its_stages():
    source = inspect.getsource(Relocalizer.localize)
    assert len(source.splitlines()) <= 40
    answer = inspect.getsource(Relocalizer.answer)
    # strip -> search, then rerank -> sample -> pose, in that order.
    stages = [source.index("QueryWindows("), source.index("search_together(")]
    stages += [
        len(source) + answer.index(word) for word in ("rerank(", "sampled_answer(", "pose_of(")
    ]
    assert stages == sorted(stages)
