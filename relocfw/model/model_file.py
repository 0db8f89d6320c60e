"""One self-describing model file: network, map, crop search and dataset metadata.

Everything needed to localize new images, loaded without Hydra or the training data:
each part is stored as the import path of its class, the options it was built with
and its state (tensors only, read back with torch's safe weights-only loader).
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

import torch

from relocfw.core.errors import DataError
from relocfw.core.pipeline import Relocalizer
from relocfw.core.values import Pose
from relocfw.model.checkpoints import read_torch_file, save_atomic

MODEL_FORMAT = 2  # 2: input normalisation and training crop_scale saved in the state
MODEL_KIND = "relocfw-model"


def class_path(obj: object) -> str:
    return f"{type(obj).__module__}.{type(obj).__qualname__}"


def import_class(path: str, source: Path) -> type:
    module, _, name = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as error:
        raise DataError(
            f"{source}: cannot import {path} ({error}); is its package installed?"
        ) from error


def save_model(
    path: Path,
    relocalizer: Relocalizer,
    options: dict[str, dict[str, Any]],
    metadata: dict[str, Any],
) -> Path:
    """Write `relocalizer` (fitted) to `path`, atomically.

    Args:
        path: the model file to write.
        relocalizer: a fitted Relocalizer.
        options: constructor options of "backbone", "index" and "crop".
        metadata: plain values describing the data (dataset settings, sizes, names).
    """
    parts = {"backbone": relocalizer.backbone, "index": relocalizer.index, "crop": relocalizer.crop}
    payload: dict[str, Any] = {
        "kind": MODEL_KIND,
        "format": MODEL_FORMAT,
        "retrieval_k": relocalizer.retrieval_k,
        "crop_samples": relocalizer.crop_samples,
        "sample_seed": relocalizer.sample_seed,
        "rerank": relocalizer.rerank,
        "metadata": metadata,
    }
    for name, part in parts.items():
        payload[name] = {"class": class_path(part), "options": dict(options.get(name, {}))}
    payload["backbone"]["state"] = {
        k: v.detach().cpu() for k, v in relocalizer.backbone.state_dict().items()
    }
    payload["index"]["state"] = relocalizer.index.state()
    if relocalizer.map_poses:
        payload["map_poses"] = torch.tensor(
            [[*p.position, *p.quaternion] for p in relocalizer.map_poses], dtype=torch.float64
        )
    save_atomic(payload, Path(path))
    return Path(path)


def load_model(
    path: Path, device: str | torch.device = "cpu", batch_size: int = 16, scoring: str = "plain"
) -> Relocalizer:
    """The Relocalizer saved in `path`, ready to localize."""
    path = Path(path)
    payload = read_torch_file(path, "model")
    if not isinstance(payload, dict) or payload.get("kind") != MODEL_KIND:
        raise DataError(f"{path} is not a relocfw model file")
    if payload.get("format") != MODEL_FORMAT:
        raise DataError(
            f"{path} is model format {payload.get('format')}; this relocfw reads format "
            f"{MODEL_FORMAT}: run `relocfw task=relocalize` again with this version to "
            "write a new one"
        )
    try:
        backbone_class = import_class(payload["backbone"]["class"], path)
        options = {**payload["backbone"]["options"], **backbone_class.rebuild_overrides}
        backbone = backbone_class(**options)
        backbone.load_state_dict(payload["backbone"]["state"])
        index = import_class(payload["index"]["class"], path)(**payload["index"]["options"])
        index.load_state(payload["index"]["state"])
        crop = import_class(payload["crop"]["class"], path)(**payload["crop"]["options"])
    except (KeyError, TypeError, RuntimeError) as error:
        raise DataError(f"{path}: damaged or incompatible model file ({error})") from error
    relocalizer = Relocalizer(
        backbone,
        index,
        crop,
        device,
        batch_size,
        payload["retrieval_k"],
        scoring,
        crop_samples=payload.get("crop_samples", 0),
        sample_seed=payload.get("sample_seed", 0),
        rerank=payload.get("rerank", 1) if scoring == "shared" else 1,
    )
    if "map_poses" in payload:
        relocalizer.map_poses = [Pose(row[:3], row[3:]) for row in payload["map_poses"].numpy()]
    relocalizer.metadata = payload["metadata"]
    return relocalizer
