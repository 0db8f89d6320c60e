"""A checkpoint is reused only for the same model: any training input changes its key.

Methods are built from composed configs exactly as the CLI builds them (build_method),
then trained or reused by relocfw.app.training_runs.train_or_reuse on the tiny synthetic scene.
"""

from dataclasses import replace

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module

from relocfw.app import training_runs
from relocfw.app.methods import build_method
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.model.checkpoints import load_checkpoint, settings_key
from relocfw.model.training import TrainingRun
from tests.conftest import TINY_MODEL

TINY = [o for o in TINY_MODEL if not o.startswith("hydra.")] + ["backbone.width=0.0625"]


def method_of(*overrides: str):
    with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
        cfg = compose("config", overrides=[*TINY, *overrides], return_hydra_config=True)
    return build_method(cfg, cfg.hydra.runtime.choices)


@pytest.fixture(scope="module")
def train_split(tiny_scene):
    frames = load_sevenscenes(tiny_scene, None, "train")
    return frames, read_images(frames, quiet=True)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("checkpoint-keys")


def train(method, frames, images, cache):
    """(checkpoint path, whether it was reused) for this method and training split."""
    checkpoint, run = training_runs.train_or_reuse(
        method.backbone,
        frames,
        images,
        method.settings,
        method.identity,
        cache,
        torch.device("cpu"),
        quiet=True,
    )
    return checkpoint, run.reused


@pytest.fixture(scope="module")
def first(train_split, cache):
    checkpoint, reused = train(method_of(), *train_split, cache)
    assert not reused
    return checkpoint


def test_the_same_settings_reuse_the_model(first, train_split, cache):
    assert train(method_of(), *train_split, cache) == (first, True)


@pytest.mark.parametrize(
    "overrides",
    [
        ["backbone.mc_samples=4"],  # a test-time option: the same trained network
        ["index=exhaustive", "crop=sweep"],  # the map and the search come after training
        ["k=3"],
    ],
)
def test_options_outside_training_reuse_the_model(first, train_split, cache, overrides):
    assert train(method_of(*overrides), *train_split, cache) == (first, True)


@pytest.mark.parametrize(
    "overrides",
    [
        ["train.lr=0.002"],
        ["train.crop_scale=1.2"],
        ["train.seed=1"],
        ["backbone.dropout=0.3"],
        ["backbone.feature_dim=32"],
        ["dataset.train_laps=2"],  # what the data is, even with the same frames given
    ],
)
def test_a_changed_training_or_backbone_option_trains_a_new_model(
    first, train_split, cache, overrides, monkeypatch
):
    # Only the checkpoint chosen matters here; training itself is stubbed for speed
    # (the moved-pose test below trains for real).
    asked = []

    def stub(backbone, data, settings, checkpoint, *args, **kwargs):
        asked.append(checkpoint)
        return TrainingRun([], reused=checkpoint.is_file())

    monkeypatch.setattr(training_runs, "train_backbone", stub)
    checkpoint, reused = train(method_of(*overrides), *train_split, cache)
    assert asked == [checkpoint]
    assert checkpoint != first and not reused


def test_one_moved_training_pose_trains_a_new_model(first, train_split, cache):
    frames, images = train_split
    moved = list(frames)
    pose = moved[5].pose
    moved[5] = replace(moved[5], pose=type(pose)(pose.position + [0.01, 0, 0], pose.quaternion))
    checkpoint, reused = train(method_of(), moved, images, cache)
    assert checkpoint != first and not reused
    assert load_checkpoint(checkpoint)["complete"]  # trained to the end, written


def test_one_turned_training_pose_trains_a_new_model(first, train_split, cache):
    frames, images = train_split
    turned = list(frames)
    pose = turned[2].pose
    half = np.radians(0.5) / 2  # half a degree about z, then normalised by Pose
    tilt = np.array([np.cos(half), 0.0, 0.0, np.sin(half)])
    w1, v1 = pose.quaternion[0], pose.quaternion[1:]
    w2, v2 = tilt[0], tilt[1:]
    product = np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])
    turned[2] = replace(turned[2], pose=type(pose)(pose.position, product))
    checkpoint, reused = train(method_of(), turned, images, cache)
    assert checkpoint != first and not reused


def test_an_option_at_its_key_default_keeps_older_models_keys():
    pytest.importorskip("efficientnet_lite_pytorch", reason="relocfw[efficientnet] not installed")
    base = ["backbone=efficientnet_lite0", "backbone.pretrained=false", "backbone.input_size=32"]

    def identity(*overrides: str) -> dict:
        with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
            cfg = compose("config", overrides=[*base, *overrides], return_hydra_config=True)
        return build_method(cfg, cfg.hydra.runtime.choices).identity["backbone"]

    head, kendall = identity(), identity("backbone.dropout_variant=kendall")
    # dropout_variant=head is what every EfficientNet model before it was: same key.
    assert "dropout_variant" not in head
    assert kendall["dropout_variant"] == "kendall"
    assert settings_key(head) != settings_key(kendall)
