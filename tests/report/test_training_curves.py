"""Training curves: per-step history in the run and its checkpoint, TensorBoard events."""

import numpy as np
import pytest
import torch

from relocfw.core.errors import ConfigError
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.model.checkpoints import load_checkpoint
from relocfw.model.training import TrainingImages, TrainSettings, train_backbone
from relocfw.plugins.posenet import PoseNet
from relocfw.report.figures import training_curve

LEARNED = TrainSettings(
    iterations=4, batch_size=4, optimizer="adam", lr=1e-2, loss="learned", checkpoint_every=2
)


@pytest.fixture(scope="module")
def data(tiny_scene):
    frames = load_sevenscenes(tiny_scene, None, "train")
    return TrainingImages(read_images(frames, quiet=True), [f.pose for f in frames], 32)


def tiny_model():
    torch.manual_seed(0)
    return PoseNet(input_size=32, width=0.125, feature_dim=32)


def test_every_step_records_losses_rate_and_learned_weights(data, tmp_path):
    checkpoint = tmp_path / "m.pt"
    run = train_backbone(tiny_model(), data, LEARNED, checkpoint, key="c", quiet=True)
    history = run.history
    for name in ("loss", "lr", "main", "aux1", "aux2", "main_position_m", "s_position"):
        assert len(history[name]) == 4, name
    assert history["loss"] == pytest.approx(run.losses)
    # The total is the heads' weighted sum; the learned weights move from their start.
    parts = np.array(history["main"]) + history["aux1"] + history["aux2"]
    assert np.allclose(parts, history["loss"], rtol=1e-5)
    assert history["s_position"][-1] != 0.0
    # The checkpoint keeps it, so a reused model still draws its curve.
    reused = train_backbone(tiny_model(), data, LEARNED, checkpoint, key="c", quiet=True)
    assert reused.reused and reused.history == load_checkpoint(checkpoint)["history"] == history
    path = training_curve(history, tmp_path / "training_curve.png")
    assert path.stat().st_size > 10_000


def test_tensorboard_events_hold_every_steps_losses(data, tmp_path):
    accumulator = pytest.importorskip(
        "tensorboard.backend.event_processing.event_accumulator",
        reason="relocfw[tensorboard] not installed",
    )
    log_dir = tmp_path / "tensorboard"
    run = train_backbone(tiny_model(), data, LEARNED, quiet=True, log_dir=log_dir)
    events = accumulator.EventAccumulator(str(log_dir))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"train/loss", "train/lr", "train/main", "train/s_orientation"} <= tags
    losses = [e.value for e in events.Scalars("train/loss")]
    assert [e.step for e in events.Scalars("train/loss")] == [1, 2, 3, 4]
    assert np.allclose(losses, run.losses, rtol=1e-6)


def test_without_tensorboard_the_option_says_what_to_install(data, tmp_path, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_tensorboard(name, *args, **kwargs):
        if name.startswith("torch.utils.tensorboard"):
            raise ImportError("no tensorboard")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_tensorboard)
    with pytest.raises(ConfigError, match=r'pip install "relocfw\[tensorboard\]"'):
        train_backbone(tiny_model(), data, LEARNED, quiet=True, log_dir=tmp_path / "tb")
