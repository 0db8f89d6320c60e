"""`relocfw`: the Hydra command line. The only module that sees a DictConfig."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from relocfw import jobs
from relocfw.errors import ConfigError, RelocfwError
from relocfw.interfaces import Backbone, CropSearch, SimilarityIndex
from relocfw.training import TrainSettings

TASKS = ("relocalize", "train")
INTERFACES = {"backbone": Backbone, "index": SimilarityIndex, "crop": CropSearch}


def build(cfg: DictConfig, group: str, **extra: Any) -> Any:
    """Instantiate the option chosen for `group`, turning failures into one message."""
    choice = HydraConfig.get().runtime.choices.get(group, "?")
    try:
        obj = instantiate(cfg[group], **extra)
    except InstantiationException as error:
        cause = error.__cause__ or error
        if isinstance(cause, RelocfwError):
            raise ConfigError(f"{group}={choice}: {cause}") from error
        raise ConfigError(f"{group}={choice}: {type(cause).__name__}: {cause}") from error
    except OmegaConfBaseException as error:
        raise ConfigError(f"{group}={choice}: {error}") from error
    expected = INTERFACES.get(group)
    if expected is not None and not isinstance(obj, expected):
        raise ConfigError(
            f"{group}={choice}: {type(obj).__qualname__} does not implement {expected.__name__}"
        )
    return obj


def train_settings(cfg: DictConfig) -> TrainSettings:
    values = OmegaConf.to_container(cfg.train, resolve=True)
    try:
        for key in ("auxiliary_weights", "learned_init"):
            if key in values:
                values[key] = tuple(values[key])
        settings = TrainSettings(**values)
    except TypeError as error:
        raise ConfigError(f"train: {error}") from error
    settings.validate()
    return settings


def pick_device(name: str) -> torch.device:
    try:
        device = torch.device(name)
    except RuntimeError as error:
        raise ConfigError(f"device: {error}") from error
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device={name}, but CUDA is not available here; use device=cpu")
    return device


def run(cfg: DictConfig) -> None:
    if cfg.task not in TASKS:
        raise ConfigError(f"task must be one of {', '.join(TASKS)}, got {cfg.task!r}")
    unknown = set(cfg.baselines) - set(jobs.BASELINES)
    if unknown:
        raise ConfigError(f"baselines: unknown {sorted(unknown)}; known: {list(jobs.BASELINES)}")
    if int(cfg.query_batch_size) < 1:
        raise ConfigError(f"query_batch_size must be at least 1, got {cfg.query_batch_size}")
    device = pick_device(cfg.device)
    settings = train_settings(cfg)
    # Seeded here, in the CLI, so the same command initialises the same network.
    torch.manual_seed(int(cfg.seed))
    backbone = build(cfg, "backbone")
    # Build every plugin before any slow work, so a bad option fails in a second.
    index = build(cfg, "index") if cfg.task == "relocalize" else None
    crop = build(cfg, "crop") if cfg.task == "relocalize" else None
    dataset = build(cfg, "dataset")
    identity = {
        "dataset": {
            k: v
            for k, v in OmegaConf.to_container(cfg.dataset, resolve=True).items()
            if k not in ("cache_dir", "quiet")
        },
        "backbone": OmegaConf.to_container(cfg.backbone, resolve=True),
    }
    quiet = bool(cfg.quiet)
    train = jobs.load_split(dataset, "train", quiet)
    if index is not None:
        index.check_map_size(len(train[0]))
    checkpoint, reused = jobs.train_or_reuse(
        backbone, *train, settings, identity, Path(cfg.cache_dir), device, quiet
    )
    print(f"model: {checkpoint} ({'reused' if reused else 'trained'})")
    if cfg.task == "train":
        return
    test = jobs.load_split(dataset, "test", quiet)
    choices = HydraConfig.get().runtime.choices
    method = f"{choices['crop']} + {choices['index']}"
    if choices["index"] == "kmeans":
        method += f" (k={cfg.index.k})"
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    jobs.relocalize(
        backbone,
        index,
        crop,
        method,
        train,
        test,
        run_dir,
        device,
        baselines=list(cfg.baselines),
        query_batch_size=int(cfg.query_batch_size),
        quiet=quiet,
    )


@hydra.main(version_base="1.3", config_path="pkg://relocfw.conf", config_name="config")
def hydra_main(cfg: DictConfig) -> None:
    try:
        run(cfg)
    except RelocfwError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)


def main() -> None:
    """Console-script entry point."""
    hydra_main()


if __name__ == "__main__":
    main()
