"""Training a method's network, or reusing the checkpoint of the same model."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from relocfw.app.config_schema import name_of
from relocfw.app.methods import Method
from relocfw.app.results import safe_name
from relocfw.core.interfaces import Backbone
from relocfw.data.frames import Frame
from relocfw.model.checkpoints import CHECKPOINT_FORMAT, settings_key
from relocfw.model.distributed import World
from relocfw.model.training import TrainingImages, TrainingRun, TrainSettings, train_backbone
from relocfw.report.figures import training_curve
from relocfw.report.units import METRES, PositionUnit


def frames_fingerprint(frames: Sequence[Frame]) -> str:
    """Changes when the training images' names or poses change, so stale models are not reused."""
    rows = [
        (f.name, np.round(f.pose.position, 6).tolist(), np.round(f.pose.quaternion, 6).tolist())
        for f in frames
    ]
    return settings_key({"frames": rows})


def train_or_reuse(
    backbone: Backbone,
    frames: Sequence[Frame],
    images: Sequence[np.ndarray],
    settings: TrainSettings,
    identity: dict[str, Any],
    cache_dir: Path,
    device: torch.device,
    quiet: bool,
    world: World | None = None,
    log_dir: Path | None = None,
) -> tuple[Path, TrainingRun]:
    """Train the backbone, or load the checkpoint of the same model trained before.

    The checkpoint is named by a hash of the dataset and backbone settings, the
    training settings and the training frames themselves.

    Returns:
        The checkpoint path, and how training went (reused, resumed or fresh).
    """
    key = settings_key(
        {
            "format": CHECKPOINT_FORMAT,
            "identity": identity,
            "train": settings.__dict__,
            "frames": frames_fingerprint(frames),
        }
    )
    checkpoint = Path(cache_dir).expanduser() / "checkpoints" / f"{key}.pt"
    data = TrainingImages(
        images, [f.pose for f in frames], backbone.input_size, settings.crop_scale
    )
    run = train_backbone(backbone, data, settings, checkpoint, key, device, quiet, world, log_dir)
    return checkpoint, run


def prepare_model(
    cfg: DictConfig,
    method: Method,
    train: tuple,
    device: torch.device,
    world: World | None = None,
    curve: Path | None = None,
    curve_dir: Path | None = None,
    unit: PositionUnit = METRES,
) -> Path:
    """Train the method's network or reuse its checkpoint; print which.

    Args:
        curve: where to draw the run's training curve (from the checkpoint's history
            when it is reused). With train.log=tensorboard, the events of a run that
            trains go to a `tensorboard/` folder beside it.
        curve_dir: instead of `curve`, a folder: the curve is then
            `training_curve_<checkpoint>.png` there, one file per distinct model.
        unit: what the curve's position errors are in (the dataset's unit).
    """
    log_dir = None
    if name_of(cfg.train.log) == "tensorboard":
        if curve is not None:
            log_dir = curve.parent / "tensorboard"
        elif curve_dir is not None:  # several models: one run each
            log_dir = curve_dir / "tensorboard" / safe_name(method.label)
    checkpoint, training = train_or_reuse(
        method.backbone,
        *train,
        method.settings,
        method.identity,
        Path(cfg.cache_dir),
        device,
        bool(cfg.quiet),
        world,
        log_dir,
    )
    if world is not None and not world.is_main:
        return checkpoint
    if curve is None and curve_dir is not None:
        curve = curve_dir / f"training_curve_{checkpoint.stem}.png"
    if curve is not None:
        history = training.history or {"loss": training.losses}  # an older checkpoint
        training_curve(history, curve, f"({checkpoint.name})", unit)
    if training.reused:
        how = "reused"
    elif training.resumed_from:
        how = f"trained, resumed from step {training.resumed_from}"
    else:
        how = "trained"
    print(f"model: {checkpoint} ({how})")
    return checkpoint
