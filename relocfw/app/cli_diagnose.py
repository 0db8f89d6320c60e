"""task=diagnose: the crop-headroom diagnostic from the command line.

The same model and map as task=relocalize (the checkpoint is trained or reused by
the same key, the map fitted with the configured index); then every crop offset of
every test query is scored (relocfw.report.diagnosis) and the files written
(relocfw.app.diagnose_task).
"""

from __future__ import annotations

from pathlib import Path

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from relocfw.app import relocalize_task
from relocfw.app.cli_methods import build, build_method, dataset_settings, prepare_model
from relocfw.app.diagnose_task import write_diagnosis
from relocfw.core.options import integer_at_least
from relocfw.core.version import VERSION
from relocfw.report.diagnosis import diagnose
from relocfw.report.units import unit_of


def diagnose_options(cfg: DictConfig) -> tuple[int, int]:
    """(curve_queries, table3_queries), checked before any slow work."""
    section = cfg.get("diagnose") or {}
    curves = integer_at_least("diagnose.curve_queries", section.get("curve_queries", 4), 0)
    table3 = integer_at_least("diagnose.table3_queries", section.get("table3_queries", 3), 0)
    return curves, table3


def run_diagnose(cfg: DictConfig, device: torch.device) -> None:
    """Train or reuse the model, fit the map, score every crop offset, write the files."""
    curve_queries, table3_queries = diagnose_options(cfg)
    choices = HydraConfig.get().runtime.choices
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    method = build_method(cfg, choices)
    dataset = build(cfg, "dataset", choices["dataset"])
    quiet = bool(cfg.quiet)
    train = relocalize_task.load_split(dataset, "train", quiet)
    method.index.check_map_size(len(train[0]))
    checkpoint = prepare_model(
        cfg, method, train, device, curve=run_dir / "training_curve.png", unit=unit_of(dataset)
    )
    test = relocalize_task.load_split(dataset, "test", quiet)
    relocalize_task.write_skipped(dataset, run_dir)
    relocalizer = method.relocalizer(device, int(cfg.query_batch_size))
    relocalizer.fit(train[1], [f.pose for f in train[0]], quiet=quiet)
    queries = diagnose(relocalizer, *test, quiet=quiet)
    scene = str(cfg.dataset.get("scene") or choices["dataset"])
    settings = {
        "crops": "every offset at stride 1 (the configured crop search is not used)",
        "backbone": choices["backbone"],
        "backbone_options": method.options["backbone"],
        "index": choices["index"],
        "index_options": method.options["index"],
        "retrieval_k": method.retrieval_k,
        "scoring": "plain (every window through the whole network)",
        "input_size": int(relocalizer.backbone.input_size),
        "crop_scale": relocalizer.crop_scale,
        "query_batch_size": relocalizer.batch_size,
        "dataset": choices["dataset"],
        "dataset_settings": dataset_settings(cfg),
        "map_images": len(train[0]),
        "test_queries": len(test[0]),
        "checkpoint": str(checkpoint),
        "curve_queries": curve_queries,
        "table3_queries": table3_queries,
        "relocfw_version": VERSION,
    }
    write_diagnosis(
        scene,
        queries,
        test[1],
        run_dir,
        settings,
        curve_queries,
        table3_queries,
        unit=unit_of(dataset),
    )
