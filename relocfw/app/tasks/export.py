"""task=export: the network of a saved model (export.model) as ONNX, for robots."""

from __future__ import annotations

import torch
from omegaconf import DictConfig

from relocfw.app.tasks.localize import model_file
from relocfw.core.sampling import configured_samples
from relocfw.model.distributed import World
from relocfw.model.model_file import load_model
from relocfw.model.onnx_export import export_destination, export_onnx, require


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    """Write the ONNX network (export.out, or beside the model file) after checking
    that onnxruntime answers as torch does. The export runs on the CPU, whatever
    `device` says: the graph is traced once, and robots run it with onnxruntime."""
    model = model_file(cfg.export.model, "export.model")
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
    print(
        f"localize with it: relocfw task=localize localize.model={model} localize.images=... "
        "(engine=onnx, the default on a CPU, runs the same network from graphs it caches "
        "in cache_dir/graphs/, keyed by the model file's content)"
    )
