"""`relocfw`: the Hydra command line. With cli_methods, cli_compare and cli_diagnose,
the only modules that see a DictConfig."""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from relocfw.app import relocalize_task
from relocfw.app.cli_compare import run_compare
from relocfw.app.cli_diagnose import run_diagnose
from relocfw.app.cli_methods import (
    build,
    build_method,
    centre_label,
    dataset_settings,
    pick_device,
    prepare_model,
)
from relocfw.app.hydra_plugins import install as install_plugin_discovery
from relocfw.app.hydra_plugins import options_help
from relocfw.app.localize_task import find_images, localize_images
from relocfw.app.plugin_discovery import conflicts, discover_options
from relocfw.app.torchrun import join_torchrun, leave_torchrun
from relocfw.core.errors import ConfigError, DataError, RelocfwError
from relocfw.core.options import integer_at_least
from relocfw.core.pipeline import Relocalizer, check_rerank, check_sampling
from relocfw.core.sampling import configured_samples
from relocfw.core.version import VERSION
from relocfw.model.distributed import World
from relocfw.model.model_file import load_model, save_model
from relocfw.model.onnx_backbone import check_onnx_scoring, onnx_relocalizer
from relocfw.model.onnx_export import export_destination, export_onnx, onnx_path, require
from relocfw.report.units import unit_of

TASKS = ("relocalize", "train", "compare", "localize", "plugins", "diagnose", "export")
BACKENDS = ("torch", "onnx")  # what runs the network of task=localize


def check_common(cfg: DictConfig) -> torch.device:
    if cfg.task not in TASKS:
        raise ConfigError(f"task must be one of {', '.join(TASKS)}, got {cfg.task!r}")
    unknown = set(cfg.baselines) - set(relocalize_task.BASELINES)
    if unknown:
        raise ConfigError(
            f"baselines: unknown {sorted(unknown)}; known: {list(relocalize_task.BASELINES)}"
        )
    integer_at_least("query_batch_size", cfg.query_batch_size, 1)
    if cfg.backend not in BACKENDS:
        raise ConfigError(f"backend must be one of {', '.join(BACKENDS)}, got {cfg.backend!r}")
    if cfg.backend != "torch" and cfg.task != "localize":
        raise ConfigError(f"backend={cfg.backend} applies to task=localize only")
    return pick_device(cfg.device)


def cli_overrides() -> set[str]:
    """Keys set on this command line (`key=value`, `+key=value`)."""
    return {o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task}


def model_file(cfg: DictConfig) -> Path:
    if not cfg.model:
        raise ConfigError("model is not set: pass model=FILE (a model.relocfw from a run)")
    return Path(cfg.model).expanduser()


def run_export(cfg: DictConfig) -> None:
    model = model_file(cfg)
    out = export_destination(model, cfg.export.out)  # refused before any work
    require("onnx", "task=export")
    require("onnxruntime", "task=export")
    relocalizer = load_model(model, "cpu")
    samples = configured_samples(relocalizer.backbone)
    if samples > 0:
        print(
            f"note: the model samples backbone.mc_samples={samples} Monte Carlo dropout "
            "masks; the ONNX network is the dropout-free one (mc_samples=0)"
        )
    differences = export_onnx(relocalizer.backbone, out)
    largest = max(differences.values())
    size = relocalizer.backbone.input_size
    print(
        f"ONNX network: {out}  (images [B,3,{size},{size}] in [0,1] -> positions, "
        f"quaternions, features; onnxruntime matches torch to {largest:.1e})"
    )
    where = f" export.out={out}" if cfg.export.out else ""
    print(f"localize with it: relocfw task=localize model={model} images=... backend=onnx{where}")


def load_for_localize(cfg: DictConfig, device: torch.device) -> Relocalizer:
    """The model file's Relocalizer, its network run by torch or onnxruntime (backend)."""
    model = model_file(cfg)
    batch, scoring = int(cfg.query_batch_size), str(cfg.scoring)
    if cfg.backend == "torch":
        return load_model(model, device, batch, scoring)
    check_onnx_scoring(scoring)
    if device.type != "cpu":
        raise ConfigError(
            f"backend=onnx runs the network with onnxruntime on the CPU; drop device={device} "
            "(or use backend=torch)"
        )
    require("onnxruntime", "backend=onnx")
    network = onnx_path(model, cfg.export.out)
    if not network.is_file():
        where = f" export.out={cfg.export.out}" if cfg.export.out else ""
        raise DataError(
            f"ONNX network not found: {network}; run relocfw task=export model={model}{where} first"
        )
    return onnx_relocalizer(load_model(model, device, batch, scoring), network)


def run_localize(cfg: DictConfig, device: torch.device) -> None:
    relocalizer = load_for_localize(cfg, device)
    # Query-time options from the command line, over what the model file kept.
    relocalizer.queries_at_once = integer_at_least("queries_at_once", cfg.queries_at_once, 1)
    given = cli_overrides()
    for key, attribute, least in (
        ("rerank", "rerank", 1),
        ("crop_samples", "crop_samples", 0),
        ("seed", "sample_seed", 0),
    ):
        if key in given:
            setattr(relocalizer, attribute, integer_at_least(key, cfg[key], least))
    check_rerank(relocalizer.rerank, relocalizer.scoring)
    check_sampling(
        relocalizer.retrieval_k,
        relocalizer.crop_samples,
        configured_samples(relocalizer.backbone),
        relocalizer.crop_scale,
    )
    images = find_images(str(cfg.images or ""))
    localize_images(relocalizer, images, Path(HydraConfig.get().runtime.output_dir), cfg.quiet)


def run(cfg: DictConfig) -> None:
    device = check_common(cfg)
    world, device = join_torchrun(str(cfg.task), device)
    try:
        run_task(cfg, device, world)
    finally:
        leave_torchrun(world)


def run_task(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    if cfg.task == "compare":
        run_compare(cfg, device)
        return
    if cfg.task == "localize":
        run_localize(cfg, device)
        return
    if cfg.task == "export":
        run_export(cfg)
        return
    if cfg.task == "diagnose":
        run_diagnose(cfg, device)
        return
    if cfg.task == "plugins":
        print(options_help())
        return
    choices = HydraConfig.get().runtime.choices
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    method = build_method(cfg, choices)
    dataset = build(cfg, "dataset", choices["dataset"])
    quiet = bool(cfg.quiet)
    # Under torchrun, rank 0 loads (and renders, for the synthetic scene) first.
    if world is not None and not world.is_main:
        world.barrier()
    train = relocalize_task.load_split(
        dataset, "train", quiet or (world is not None and not world.is_main)
    )
    if world is not None and world.is_main:
        world.barrier()
    if cfg.task == "relocalize":
        method.index.check_map_size(len(train[0]))
    checkpoint = prepare_model(
        cfg,
        method,
        train,
        device,
        world,
        curve=run_dir / "training_curve.png",
        unit=unit_of(dataset),
    )
    if cfg.task == "train":
        relocalize_task.write_skipped(dataset, run_dir)
        return
    test = relocalize_task.load_split(dataset, "test", quiet)
    relocalize_task.write_skipped(dataset, run_dir)
    relocalizer = method.relocalizer(device, int(cfg.query_batch_size))
    relocalize_task.relocalize(
        relocalizer,
        method.label,
        train,
        test,
        run_dir,
        baselines=list(cfg.baselines),
        centre_label=centre_label(cfg, choices),
        quiet=quiet,
        unit=unit_of(dataset),
    )
    metadata = {
        "method": method.label,
        "dataset": choices["dataset"],
        "dataset_settings": dataset_settings(cfg),
        "map_images": len(train[0]),
        "checkpoint": str(checkpoint),
        "relocfw_version": VERSION,
    }
    model = save_model(run_dir / "model.relocfw", relocalizer, method.options, metadata)
    print(f"model file: {model}  (relocfw task=localize model={model} images=...)")


@hydra.main(version_base="1.3", config_path="pkg://relocfw.conf", config_name="config")
def hydra_main(cfg: DictConfig) -> None:
    try:
        run(cfg)
    except RelocfwError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)


def main() -> None:
    """Console-script entry point. Ctrl-C ends it with one line and exit status 130
    (128 + SIGINT, as a shell reports it), not a traceback."""
    try:
        install_plugin_discovery()
        clashes = conflicts(discover_options())
        for line in clashes:
            print(f"warning: {line}", file=sys.stderr)
        hydra_main()
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
