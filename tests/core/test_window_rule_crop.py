"""crop=rule: a selection rule over every window's answer, live, as the offline study."""

import numpy as np
import pytest
import torch

from relocfw.core.errors import ConfigError, DataError, RelocfwError
from relocfw.core.interfaces import Backbone
from relocfw.core.pipeline import Relocalizer
from relocfw.core.query_options import QueryOptions
from relocfw.core.values import Crop, Pose, PoseOutput
from relocfw.core.window_rules import (
    consensus,
    retrieval_consistency,
    robust_mean,
    soft_min_distance,
)
from relocfw.model.model_file import load_model, save_model
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop
from relocfw.plugins.window_rule_crop import WindowRuleSearch
from relocfw.report.diagnosis import diagnose
from relocfw.report.window_recording import load_windows, save_windows


class ColourPose(Backbone):
    """A toy network: descriptor = mean colour of the window's thirds; the pose is a
    fixed smooth function of it, so every window has its own, known answer."""

    input_size = 12
    feature_dim = 9

    def __init__(self) -> None:
        super().__init__()
        generator = torch.Generator().manual_seed(3)
        self.to_position = torch.randn(9, 3, generator=generator)
        self.to_rotation = torch.randn(9, 3, generator=generator) * 0.3
        self.scale = torch.nn.Parameter(torch.ones(1))  # a weight, so model files hold one

    def forward(self, images):
        thirds = images.unflatten(3, (3, 4)).mean(dim=(2, 4))  # [n, 3 channels, 3 thirds]
        features = thirds.flatten(1) * self.scale
        half_angles = features @ self.to_rotation
        quaternions = torch.cat([torch.ones(len(images), 1), half_angles], dim=1)
        return PoseOutput(features @ self.to_position, quaternions, features)


def image(seed: int) -> np.ndarray:
    """A 12 x 40 image whose colours change along its width, so windows differ."""
    rng = np.random.default_rng(seed)
    columns = np.cumsum(rng.normal(0, 20, size=(40, 3)), axis=0) + 128
    return np.clip(np.broadcast_to(columns, (12, 40, 3)), 0, 255).astype(np.uint8)


@pytest.fixture
def fitted():
    """A map of 12 images with poses, a test image, and a maker of fitted pipelines."""
    torch.manual_seed(0)
    backbone = ColourPose().eval()
    images = [image(seed) for seed in range(12)]
    poses = [Pose(np.random.default_rng(s).normal(size=3), [1, 0, 0, 0]) for s in range(12)]

    def relocalizer(search, **options):
        pipeline = Relocalizer(backbone, ExhaustiveIndex(), search, QueryOptions(**options))
        pipeline.fit(images, poses)
        return pipeline

    return relocalizer, images, poses


@pytest.mark.parametrize("rule", ["retrieval_consistency", "consensus", "mean", "robust_mean"])
def test_the_live_search_chooses_the_window_the_recorded_rule_chooses(fitted, tmp_path, rule):
    relocalizer, images, poses = fitted
    live = relocalizer(WindowRuleSearch(rule=rule, neighbours=3))
    # The offline route: diagnose records every window, the rule reads the file.
    queries = [image(100 + i) for i in range(4)]
    frames = [type("F", (), {"name": f"q{i}", "pose": poses[i]})() for i in range(4)]
    recorded = diagnose(live, frames, queries, map_features=live.describe(images), neighbours=3)
    save_windows(tmp_path / "w.npz", recorded, poses)
    offline = {
        "retrieval_consistency": retrieval_consistency,
        "consensus": consensus,
        "mean": lambda w: soft_min_distance(w, np.inf),
        "robust_mean": robust_mean,
    }[rule]
    for query, record in zip(queries, load_windows(tmp_path / "w.npz"), strict=True):
        answer = live.localize(query)
        chosen = offline(record.windows)
        assert np.allclose(answer.pose.position, chosen.position)
        assert np.allclose(answer.pose.quaternion, chosen.quaternion) or np.allclose(
            answer.pose.quaternion, -chosen.quaternion
        )
        assert type(answer.crop) is Crop  # a blend is reported on a plain window


def test_min_distance_and_centre_rules_are_the_sweep_and_the_centre_crop(fitted):
    relocalizer, _, _ = fitted
    query = image(7)
    pairs = [("min_distance", SweepCrop()), ("centre", CentreCrop())]
    for rule, reference in pairs:
        got = relocalizer(WindowRuleSearch(rule=rule)).localize(query)
        assert got.crop == relocalizer(reference).localize(query).crop


def test_unknown_rule_and_shared_scoring_are_refused(fitted):
    relocalizer, _, _ = fitted
    with pytest.raises(ConfigError, match="crop.rule"):
        WindowRuleSearch(rule="fancy")
    with pytest.raises(ConfigError, match="crop.tau"):
        WindowRuleSearch(rule="soft_min_distance", tau=0)
    with pytest.raises(ConfigError, match="crop_samples"):
        Relocalizer(
            ColourPose(), ExhaustiveIndex(), WindowRuleSearch(), QueryOptions(crop_samples=4)
        )
    with pytest.raises(ConfigError, match="scoring=plain"):
        Relocalizer(
            ColourPose(), ExhaustiveIndex(), WindowRuleSearch(), QueryOptions(scoring="shared")
        )


def test_it_needs_the_map_poses_and_a_fitted_map():
    pipeline = Relocalizer(ColourPose().eval(), ExhaustiveIndex(), WindowRuleSearch())
    with pytest.raises(DataError, match="pose of every map image"):
        pipeline.fit([image(1), image(2)])
    with pytest.raises(DataError, match="Relocalizer.fit first"):
        WindowRuleSearch().state()


def test_a_plain_distance_function_is_told_it_needs_a_relocalizer(fitted):
    relocalizer, _, _ = fitted
    search = relocalizer(WindowRuleSearch()).search
    with pytest.raises(RelocfwError, match="run it through a Relocalizer"):
        search.search(40, 12, lambda crops: np.zeros(len(crops)))


def test_a_model_file_keeps_the_searchs_map(tmp_path):
    torch.manual_seed(0)
    backbone_options = {"input_size": 32, "width": 0.125, "feature_dim": 16}
    search = WindowRuleSearch(rule="retrieval_consistency", neighbours=2)
    pipeline = Relocalizer(PoseNet(**backbone_options).eval(), ExhaustiveIndex(), search)
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (36, 48, 3), dtype=np.uint8) for _ in range(4)]
    pipeline.fit(images, [Pose(rng.normal(size=3), [1, 0, 0, 0]) for _ in range(4)])
    options = {
        "backbone": backbone_options,
        "crop": {"rule": "retrieval_consistency", "neighbours": 2},
    }
    loaded = load_model(save_model(tmp_path / "model.relocfw", pipeline, options, {}))
    query = rng.integers(0, 255, (36, 60, 3), dtype=np.uint8)
    assert loaded.localize(query).crop == pipeline.localize(query).crop
    assert np.allclose(loaded.search.map_positions, pipeline.search.map_positions)
    assert loaded.search.distance_scale == pipeline.search.distance_scale
