"""task=plugins: every option of every group, with its interface and package."""

from __future__ import annotations

import torch
from omegaconf import DictConfig

from relocfw.app.hydra_plugins import options_help
from relocfw.model.distributed import World


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    print(options_help())
