"""The structure refiners' settings chosen on validation blocks (docs/results/structure.md,
docs/scene_coordinates.md) are what `refine=features`, `refine=features_rgb` and
`refine=scene_coordinates` compose to: an edit of
conf/refine/*.yaml that drops or changes one fails here, not silently in a benchmark."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_module

CHOSEN = {
    "features": {
        "structure": "depth",
        "count": 10,
        "max_error_px": 8.0,
        "min_inliers": 12,
        "image_scale": 0.5,
        "rematch": "near",
        "rematch_answer": "more_inliers",
        "triangulation.epipolar_px": 4.0,
        "triangulation.max_reprojection_px": 4.0,
    },
    "features_rgb": {
        "structure": "triangulated",
        "count": 20,
        "max_error_px": 16.0,
        "min_inliers": 8,
        "image_scale": 0.5,
        "rematch": "near",
        "rematch_answer": "more_inliers",
        "triangulation.epipolar_px": 6.0,
        "triangulation.max_reprojection_px": 6.0,
        "triangulation.method": "tracks",
    },
    "features_colmap": {
        "structure": "colmap",
        "image_scale": 0.5,
        "rematch": "near",
        "rematch_answer": "more_inliers",
    },
    # docs/scene_coordinates.md, "Settings tried on validation".
    "scene_coordinates": {"head_width": "auto", "max_error_px": "auto"},
}


@pytest.mark.parametrize("refiner", sorted(CHOSEN))
def test_the_refine_config_holds_the_chosen_settings(refiner):
    with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
        config = compose("config", overrides=[f"refine={refiner}"])
    for key, chosen in CHOSEN[refiner].items():
        value = config.refine
        for part in key.split("."):
            value = value[part]
        assert value == chosen, f"refine={refiner}: refine.{key} is {value!r}, chosen {chosen!r}"
