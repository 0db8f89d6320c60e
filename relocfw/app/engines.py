"""engine=auto|torch|onnx: what runs a task's network passes (relocfw.model.onnx_engine).

Every task that localizes (relocalize, compare, diagnose, localize) puts its
Relocalizer through `on_engine` before fitting the map, so the map and the queries
are described by the same engine. Training never goes through here: it is torch's.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from relocfw.app.config_schema import name_of
from relocfw.core.errors import ConfigError
from relocfw.core.pipeline import Relocalizer
from relocfw.model.onnx_engine import EngineOptions, EngineUnavailableError, onnx_engine


def warn(line: str) -> None:
    """Notes go to stderr, as the CLI's other notes do; results stay on stdout."""
    print(line, file=sys.stderr)


def engine_options(cfg: DictConfig) -> EngineOptions:
    onnx = cfg.onnx
    threads = None if onnx.threads is None else int(onnx.threads)
    return EngineOptions(threads=threads, int8=name_of(onnx.int8), spinning=bool(onnx.spinning))


def wanted_engine(cfg: DictConfig, device: torch.device) -> str:
    """ "torch" or "onnx" for this run; ConfigError for onnx options that cannot apply."""
    engine = name_of(cfg.engine)
    options = engine_options(cfg)  # checked whatever the engine: a bad value is a typo
    if engine == "auto":
        engine = "onnx" if device.type == "cpu" else "torch"
    if engine == "onnx" and device.type != "cpu":
        raise ConfigError(
            f"engine=onnx runs the network with onnxruntime on the CPU, but device={device}: "
            "drop device (or use engine=torch, or engine=auto: torch on a GPU)"
        )
    if engine == "torch" and options.int8 != "none":
        why = "engine=torch" if name_of(cfg.engine) == "torch" else f"device={device}"
        raise ConfigError(
            f"onnx.int8={options.int8} quantises the onnxruntime graphs, but the network "
            f"runs on torch here ({why}): use engine=onnx on a CPU, or drop onnx.int8"
        )
    return engine


def on_engine(
    cfg: DictConfig,
    relocalizer: Relocalizer,
    owner: Path,
    device: torch.device,
    calibration: Sequence[np.ndarray] | None = None,
) -> Relocalizer:
    """`relocalizer` with its network run by the configured engine.

    Args:
        owner: the checkpoint or model file the weights come from: the engine's graphs
            are cached beside it.
        calibration: map images, for onnx.int8=static.

    With engine=onnx (or auto on a CPU) the graphs are exported or reused; when that
    is not possible the run goes on with torch and one line says why. The returned
    relocalizer shares the map, search and refiner of `relocalizer`.
    """
    if wanted_engine(cfg, device) == "torch":
        return relocalizer
    options = engine_options(cfg)
    try:
        backbone = onnx_engine(relocalizer.backbone, owner, options, calibration, say=warn)
    except EngineUnavailableError as error:
        warn(f"note: {error}; the network runs on torch (engine=torch silences this)")
        return relocalizer
    swapped = relocalizer.replace(backbone=backbone)
    if not bool(cfg.quiet):
        print(f"engine: {backbone.description}")
    return swapped
