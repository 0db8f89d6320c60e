"""task=train: train the configured method's network, or find it trained, and stop.

`trained` is also the first half of task=relocalize: the same model by the same key.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from relocfw.app.methods import Method, build, build_method
from relocfw.app.splits import load_split, write_skipped
from relocfw.app.training_runs import prepare_model
from relocfw.app.validation_block import calibrate_options, carve_validation
from relocfw.data.frames import Frame
from relocfw.model.distributed import World
from relocfw.report.calibration import Calibration
from relocfw.report.units import unit_of


@dataclass
class Trained:
    """A method whose network is trained, with the data it was trained on."""

    method: Method
    dataset: Any
    train: tuple[list[Frame], list[np.ndarray]]
    checkpoint: Path
    run_dir: Path
    # The validation block held out of `train` to calibrate error bounds (calibrate.share).
    calibration: Calibration | None = None


def trained(
    cfg: DictConfig, device: torch.device, world: World | None, map_size: bool = False
) -> Trained:
    """Build the method (every option checked first), load the training split, then
    train the network or reuse its checkpoint.

    Args:
        map_size: check that the index can be fitted on the training split, before
            training (a map is fitted after it).
    """
    choices = HydraConfig.get().runtime.choices
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    method = build_method(cfg, choices)
    calibrate_options(cfg)  # before any image is read
    dataset = build(cfg, "dataset", choices["dataset"])
    quiet = bool(cfg.quiet)
    # Under torchrun, rank 0 loads (and renders, for the synthetic scene) first.
    if world is not None and not world.is_main:
        world.barrier()
    train = load_split(dataset, "train", quiet or (world is not None and not world.is_main))
    if world is not None and world.is_main:
        world.barrier()
    # Held out before training: the network must not have seen the block it is judged on.
    train, calibration = carve_validation(cfg, train)
    if map_size:
        method.index.check_map_size(len(train[0]))
        if method.refiner is not None:
            method.refiner.check_map(train[0])
    checkpoint = prepare_model(
        cfg,
        method,
        train,
        device,
        world,
        curve=run_dir / "training_curve.png",
        unit=unit_of(dataset),
    )
    return Trained(method, dataset, train, checkpoint, run_dir, calibration)


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    done = trained(cfg, device, world)
    write_skipped(done.dataset, done.run_dir)
