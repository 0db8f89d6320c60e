"""engine=auto|torch|onnx|ncnn: what runs a task's network passes
(relocfw.model.onnx_engine, relocfw.model.ncnn_engine).

Every task that localizes (relocalize, compare, diagnose, localize) puts its
Relocalizer through `on_engine` before fitting the map, so the map and the queries
are described by the same engine. Training never goes through here: it is torch's.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from relocfw.app.config_schema import name_of
from relocfw.app.devices import pick_device
from relocfw.core.atomic_files import atomic_write
from relocfw.core.errors import ConfigError
from relocfw.core.pipeline import Relocalizer
from relocfw.model import cpu_flags
from relocfw.model.ncnn_engine import ncnn_engine
from relocfw.model.onnx_backbone import OnnxBackbone
from relocfw.model.onnx_engine import (
    STATIC_MODES,
    EngineOptions,
    EngineUnavailableError,
    adopt_shipped_graphs,
    graph_home,
    graph_path,
    onnx_engine,
)
from relocfw.model.onnx_graphs import KINDS

# The engines that run on the CPU only, and the library each runs the network with.
CPU_ENGINES = {"onnx": "onnxruntime", "ncnn": "ncnn"}


def warn(line: str) -> None:
    """Notes go to stderr, as the CLI's other notes do; results stay on stdout."""
    print(line, file=sys.stderr)


def engine_options(cfg: DictConfig, *, scout: bool = False) -> EngineOptions:
    """The onnx.* options; `scout`: the query's scoring is scout (the int8 graph then
    only scores candidates)."""
    onnx = cfg.onnx
    threads = None if onnx.threads is None else int(onnx.threads)
    return EngineOptions(
        threads=threads, int8=name_of(onnx.int8), spinning=bool(onnx.spinning), scout=scout
    )


def scout_asked(cfg: DictConfig) -> bool:
    """query.scoring=scout set in the config (task=localize may read it from the model
    file instead: `on_engine` checks that one)."""
    query = cfg.get("query") or {}
    return name_of(query.get("scoring")) == "scout"


def check_scout(engine: str) -> None:
    """ConfigError unless onnxruntime runs the float32 and int8 graphs scout scoring
    needs (the int8 mode itself is checked by EngineOptions)."""
    if engine != "onnx":
        runs = "torch" if engine == "torch" else f"engine={engine}"
        raise ConfigError(
            f"query.scoring=scout scores candidate crops with onnxruntime's int8 graph, "
            f"but the network runs on {runs} here: use engine=onnx (a CPU device) with "
            f"onnx.int8=static, or query.scoring=plain"
        )


def wanted_engine(cfg: DictConfig, device: torch.device) -> str:
    """The engine this run uses, "torch", "onnx" or "ncnn"; ConfigError for engine
    options that cannot apply."""
    engine = name_of(cfg.engine)
    if engine == "auto":
        engine = "onnx" if device.type == "cpu" else "torch"
    scout = scout_asked(cfg)
    if scout:
        check_scout(engine)
    # Checked whatever the engine: a bad value is a typo.
    options = engine_options(cfg, scout=scout)
    if engine in CPU_ENGINES and device.type != "cpu":
        raise ConfigError(
            f"engine={engine} runs the network with {CPU_ENGINES[engine]} on the CPU, but "
            f"device={device}: drop device (or use engine=torch, or engine=auto: torch on a GPU)"
        )
    if engine == "ncnn" and options.int8 != "none":
        raise ConfigError(
            f"onnx.int8={options.int8} quantises onnxruntime's graphs, but engine=ncnn runs "
            "ncnn's float32 networks: use engine=onnx for int8, or drop onnx.int8"
        )
    if engine == "ncnn" and options.spinning:
        raise ConfigError(
            "onnx.spinning=true sets onnxruntime's threads, but engine=ncnn runs ncnn, "
            "whose threads wait as its OpenMP runtime decides: drop onnx.spinning"
        )
    if engine == "torch" and options.int8 != "none":
        why = "engine=torch" if name_of(cfg.engine) == "torch" else f"device={device}"
        raise ConfigError(
            f"onnx.int8={options.int8} quantises the onnxruntime graphs, but the network "
            f"runs on torch here ({why}): use engine=onnx on a CPU, or drop onnx.int8"
        )
    if engine == "onnx" and options.int8 == "static_8bit":
        # Refused here, before any training, not only when the graphs are made.
        why = cpu_flags.int8_saturation_reason()
        if why is not None:
            raise ConfigError(f"onnx.int8=static_8bit cannot run here: {why}")
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
            are cached beside a checkpoint (it lies in cache_dir), and for a model file
            in cache_dir/graphs/, keyed by its content (`graph_home`), never beside it;
            graphs kept beside a model file (task=relocalize's static int8 ones) are
            copied there first.
        calibration: map images, for onnx.int8=static / static_8bit.

    With engine=auto on a CPU the graphs are exported or reused; when that is not
    possible the run goes on with torch and one line says why. engine=onnx or ncnn,
    or any onnx.int8, was asked for by name: not getting it is a ConfigError, so a row
    labelled int8 never reports torch's numbers. The returned relocalizer shares the
    map, search and refiner of `relocalizer`.
    """
    engine = wanted_engine(cfg, device)
    scout = relocalizer.options.scoring == "scout"  # a model file's scoring too
    # Set by the model file, not the command line: say so, the user never typed it.
    origin = "" if scout_asked(cfg) or not scout else " (query.scoring=scout is the model file's)"
    try:
        if scout:
            check_scout(engine)
        options = engine_options(cfg, scout=scout)
    except ConfigError as error:
        raise ConfigError(f"{error}{origin}") from error
    if engine == "torch":
        return relocalizer
    cache_dir = cfg.get("cache_dir")
    home = graph_home(owner, Path(str(cache_dir)) if cache_dir else None)
    home = adopt_shipped_graphs(owner, home)
    try:
        if engine == "ncnn":
            backbone = ncnn_engine(relocalizer.backbone, home, options, say=warn)
        else:
            with quiet_quantisation():
                backbone = onnx_engine(relocalizer.backbone, home, options, calibration, say=warn)
    except EngineUnavailableError as error:
        if name_of(cfg.engine) != "auto" or options.int8 != "none":
            asked = f"engine={engine}" if options.int8 == "none" else f"onnx.int8={options.int8}"
            instead = "engine=onnx runs onnxruntime; " if engine == "ncnn" else ""
            # int8 is never replaced by torch, whatever the engine: no fallback to offer.
            hint = f" ({instead}engine=auto falls back to torch)" if options.int8 == "none" else ""
            message = f"{asked} cannot run: {error}{hint}"
            raise ConfigError(message) from error
        warn(f"note: {error}; the network runs on torch (engine=torch silences this)")
        return relocalizer
    swapped = relocalizer.replace(backbone=backbone)
    if not bool(cfg.quiet):
        print(f"engine: {backbone.description}")
    return swapped


@contextmanager
def quiet_quantisation() -> Iterator[None]:
    """onnxruntime's quantiser logs every rescaled weight at INFO on the root logger,
    which Hydra prints: hundreds of lines per graph. Warnings still show. Here, in the
    CLI, because it changes the process's logging while it runs."""
    previous = logging.root.manager.disable
    logging.disable(logging.INFO)
    try:
        yield
    finally:
        logging.disable(previous)


def keep_graphs_beside(relocalizer: Relocalizer, checkpoint: Path, model: Path) -> None:
    """Copy the checkpoint's static int8 graphs (and the float graphs they were made
    from) beside a model file, so task=localize can use them: they cannot be remade
    there, having no map images to calibrate on."""
    backbone = relocalizer.backbone
    if not isinstance(backbone, OnnxBackbone) or backbone.int8 not in STATIC_MODES:
        return
    for kind in backbone.sessions:
        for mode in ("none", backbone.int8):
            source = graph_path(checkpoint, KINDS[kind], mode)
            if source.is_file():
                with atomic_write(graph_path(model, KINDS[kind], mode), "wb") as stream:
                    stream.write(source.read_bytes())


def check_common(cfg: DictConfig) -> torch.device:
    """What every task needs checked first: the device, and the engine's options."""
    device = pick_device(cfg.device)
    wanted_engine(cfg, device)
    return device
