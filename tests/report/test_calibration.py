"""Calibrating a fitted pipeline's error bounds in process: the bounds it gives its
answers, which answers they describe (a model file without the refiner, changed query
options, another search), the signal a refiner without confidence falls to, and the
calibrate options' checks."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from relocfw import ConfigError, DataError, PoseRefiner, QueryOptions, Refined, Relocalizer
from relocfw.app.validation_block import calibrate_options, carve_validation
from relocfw.core.trust_signal import CONFIDENCE, NONE, SPREAD, signal_name_of
from relocfw.core.values import Crop, Localization, Pose
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.model.model_file import load_model, save_model
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.retrieval_refiner import RetrievalRefiner
from relocfw.plugins.sweep_crop import SweepCrop
from relocfw.report.calibration import Calibration, calibrate_relocalizer


@pytest.fixture(scope="module")
def scene(tiny_scene):
    train = load_sevenscenes(tiny_scene, None, "train")
    return train, read_images(train, quiet=True)


def tiny_pipeline(refiner=None, search=None):
    options = {"input_size": 32, "width": 0.0625, "feature_dim": 16}
    torch.manual_seed(0)
    backbone = PoseNet(**options)
    relocalizer = Relocalizer(
        backbone, ExhaustiveIndex(), search or CentreCrop(), QueryOptions(), refiner=refiner
    )
    return relocalizer, options


def calibrated(scene, refiner=None):
    """A pipeline fitted on the first 10 frames and calibrated on the last 6."""
    frames, images = scene
    relocalizer, options = tiny_pipeline(refiner)
    relocalizer.fit(images[:10], [f.pose for f in frames[:10]], frames=frames[:10])
    block = Calibration(frames[10:], images[10:], coverage=0.8, bins=3)
    bounds, validation = calibrate_relocalizer(relocalizer, block, quiet=True)
    return relocalizer, options, bounds, validation


def answer(confidence=math.nan, fell_back=False, spread=math.nan) -> Localization:
    pose = Pose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    return Localization(
        pose,
        Crop(0, 0, 1),
        0.0,
        1,
        0.0,
        position_spread=spread,
        orientation_spread_deg=spread,
        refine_confidence=confidence,
        fell_back=fell_back,
    )


def test_a_calibrated_pipeline_bounds_every_answer_by_its_validation_errors(scene):
    relocalizer, _, bounds, validation = calibrated(scene, RetrievalRefiner(k=2))
    assert bounds.signal == CONFIDENCE and bounds.validation_size == 6
    # 6 answers at 80%: rank ceil(7 * 0.8) = 6, the largest validation error, in one bin.
    errors = validation.position_errors()
    assert bounds.position.bounds.tolist() == [pytest.approx(errors.max())]
    found = relocalizer.localize(scene[1][0])
    assert found.position_bound == pytest.approx(errors.max())
    assert math.isfinite(found.orientation_bound_deg)


def test_bounds_of_a_refiner_left_out_of_the_model_file_are_left_out_too(scene, tmp_path):
    class Unstorable(PoseRefiner):
        def fit(self, views, descriptors, quiet=True):
            pass

        def refine(self, query):
            return Refined(query.network_pose, confidence=3.0)

    relocalizer, options, bounds, _ = calibrated(scene, Unstorable())
    assert bounds.signal == CONFIDENCE
    path = save_model(tmp_path / "m.relocfw", relocalizer, {"backbone": options}, {})
    # The loaded model answers with the network's pose and no confidence: bounds
    # calibrated on the refiner's answers would describe other answers.
    assert load_model(path).bounds is None


def test_query_options_that_change_answers_drop_the_bounds(scene, tmp_path):
    relocalizer, options, bounds, _ = calibrated(scene)
    assert bounds.signal == NONE
    path = save_model(tmp_path / "m.relocfw", relocalizer, {"backbone": options}, {})
    assert load_model(path).bounds is not None
    assert load_model(path, overrides={"batch_size": 3}).bounds is not None
    # The limits on which queries are taken change no answer either.
    assert load_model(path, overrides={"max_aspect": 20.0, "max_candidates": 99}).bounds is not None
    changed = load_model(path, overrides={"sample_seed": 7})
    assert changed.bounds is None
    assert changed.metadata["bounds_dropped_for"] == ["sample_seed"]
    assert np.isnan(changed.localize(scene[1][0]).position_bound)
    # In process likewise: another search or other options, not another network.
    assert relocalizer.replace(search=SweepCrop()).bounds is None
    assert relocalizer.replace(options=QueryOptions(sample_seed=7)).bounds is None
    assert relocalizer.replace(backbone=relocalizer.backbone).bounds is bounds


def test_a_forged_file_with_confidence_bounds_and_no_refiner_is_refused(scene, tmp_path):
    relocalizer, options, _, _ = calibrated(scene, RetrievalRefiner(k=2))
    path = save_model(tmp_path / "m.relocfw", relocalizer, {"backbone": options}, {})
    payload = torch.load(path, weights_only=True)
    del payload["refine"]
    torch.save(payload, path)
    with pytest.raises(DataError, match="error_bounds are ranked by a refiner's confidence"):
        load_model(path)


def test_a_refiner_without_confidence_falls_to_the_spread_then_to_none():
    assert signal_name_of([answer(confidence=5.0)], refined=True) == CONFIDENCE
    assert signal_name_of([answer(spread=0.2)], refined=True) == SPREAD
    assert signal_name_of([answer()], refined=True) == NONE
    assert signal_name_of([answer(spread=0.2)], refined=False) == SPREAD


def config(**calibrate):
    return OmegaConf.create({"calibrate": {"share": 0.0, "coverage": 0.9, "bins": 3, **calibrate}})


def test_calibrate_options_are_checked_even_when_calibration_is_off():
    with pytest.raises(
        ConfigError, match=r"calibrate.coverage must be between 0.5 and 0.999 \(e.g. 0.9\), got 9"
    ):
        calibrate_options(config(coverage=9))
    with pytest.raises(ConfigError, match="calibrate.bins must be at least 1"):
        calibrate_options(config(bins=0))
    assert calibrate_options(config()).share == 0.0


def test_the_validation_block_is_the_end_of_the_training_recording(scene):
    # 24 frames in recording order (the tiny scene's 16, and 8 more named after them).
    frames = list(scene[0]) + [dataclasses.replace(f, name=f"{f.name}b") for f in scene[0][:8]]
    images = list(scene[1]) + list(scene[1][:8])
    train = (frames, images)
    (kept, kept_images), block = carve_validation(config(share=0.5, coverage=0.8), train)
    assert [f.name for f in kept] == [f.name for f in frames[:12]]
    assert [f.name for f in block.frames] == [f.name for f in frames[12:]]
    assert len(kept_images) == 12 and block.images[0] is images[12]
    assert block.coverage == 0.8 and block.bins == 3
    assert carve_validation(config(), train) == (train, None)
    with pytest.raises(ConfigError, match="holds out 3 of the 24 training frames; at least 10"):
        carve_validation(config(share=0.1), train)


def test_compare_rows_with_different_calibrate_options_are_refused():
    from relocfw.app.tasks.compare import one_calibration

    same = {(0, None, "A"): (config(share=0.2), {}), (0, None, "B"): (config(share=0.2), {})}
    one_calibration(same)
    differ = {(0, None, "A"): (config(share=0.2), {}), (0, None, "B"): (config(share=0.3), {})}
    with pytest.raises(ConfigError, match="compare rows 'A', 'B' set different calibrate"):
        one_calibration(differ)
