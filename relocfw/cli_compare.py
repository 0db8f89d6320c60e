"""task=compare: compose every method of compare.methods, run each on every scene."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
from hydra import compose
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from relocfw import jobs
from relocfw.cli_methods import build, build_method, prepare_model
from relocfw.compare_job import MapView, write_comparison
from relocfw.errors import ConfigError
from relocfw.evaluation import MethodResult, evaluate
from relocfw.pipeline import Relocalizer


def compose_method(overrides: list[str], name: str) -> tuple[DictConfig, Mapping[str, str]]:
    try:
        cfg = compose(config_name="config", overrides=overrides, return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as error:
        raise ConfigError(f"compare.methods.{name}: {error}") from error
    return cfg, cfg.hydra.runtime.choices


def row_label(name: str, overrides: list[str], method_cfg: DictConfig) -> str:
    """The row's name, saying so when dropout is sampled although the row did not ask.

    `backbone.mc_samples=N` on the command line applies to every row: a row called
    "PoseNet" would otherwise hide that its answers are Monte Carlo means.
    """
    samples = int(method_cfg.backbone.get("mc_samples", 0))
    asked = any(o.startswith(("backbone.mc_samples", "backbone=")) for o in overrides)
    return f"{name} (x{samples} MC dropout)" if samples and not asked else name


def run_compare(cfg: DictConfig, device: torch.device) -> None:
    """Every method of compare.methods on every scene; each model trained once."""
    methods = OmegaConf.to_container(cfg.compare.methods, resolve=True)
    if not methods:
        raise ConfigError("compare.methods is empty")
    scenes = list(cfg.compare.scenes or [None])
    reference = str(cfg.compare.reference)
    if reference not in methods:
        raise ConfigError(f"compare.reference={reference!r} is not in compare.methods")
    base = [
        o
        for o in HydraConfig.get().overrides.task
        if not o.lstrip("~+").startswith(("task=", "compare."))
    ]
    quiet = bool(cfg.quiet)
    crop_seeds = [int(s) for s in cfg.compare.crop_seeds or []]
    # Compose and build every method first: a typo fails before hours of training.
    plans, rows = {}, {}
    for scene in scenes:
        scene_override = [f"dataset.scene={scene}"] if scene is not None else []
        for name, overrides in methods.items():
            method_cfg, choices = compose_method(base + scene_override + list(overrides), name)
            plans[scene, name] = (method_cfg, choices)
            rows[name] = row_label(name, list(overrides), method_cfg)
    results, training, maps, seed_runs = {}, {}, {}, {}
    for scene in scenes:
        first_cfg, first_choices = plans[scene, next(iter(methods))]
        dataset = build(first_cfg, "dataset", first_choices["dataset"])
        label = scene or first_choices["dataset"]
        train = jobs.load_split(dataset, "train", quiet)
        test = jobs.load_split(dataset, "test", quiet)
        jobs.write_skipped(dataset, Path(HydraConfig.get().runtime.output_dir))
        results[label], training[label], maps[label] = {}, train[0], None
        seed_runs[label] = {}
        for name in methods:
            method_cfg, choices = plans[scene, name]
            method = build_method(method_cfg, choices, label=rows[name])
            method.index.check_map_size(len(train[0]))
            prepare_model(method_cfg, method, train, device)
            relocalizer = method.relocalizer(device, int(cfg.query_batch_size))
            result, features = jobs.run_method(rows[name], relocalizer, train, test, quiet)
            results[label][rows[name]] = result
            if "seed" in method_cfg.crop and len(crop_seeds) > 1:
                seed_runs[label][rows[name]] = rerun_crop_seeds(
                    method_cfg, choices, relocalizer, result, test, crop_seeds, quiet
                )
            if maps[label] is None and hasattr(method.index, "centres"):
                standardised = method.index.zscore(features)
                labels = method.index.assign(features)
                maps[label] = MapView(standardised, method.index.centres, labels)
    write_comparison(
        results,
        training,
        maps,
        rows[reference],
        Path(HydraConfig.get().runtime.output_dir),
        seed=int(cfg.seed),
        seed_runs=seed_runs,
    )


def rerun_crop_seeds(
    method_cfg: DictConfig,
    choices: Mapping[str, str],
    relocalizer: Relocalizer,
    result: MethodResult,
    test: tuple,
    crop_seeds: list[int],
    quiet: bool,
) -> dict[int, MethodResult]:
    """The method's test split again with each crop-search seed; model and map reused."""
    runs = {}
    configured = relocalizer.crop
    try:
        for seed in crop_seeds:
            if seed == int(method_cfg.crop.seed):
                runs[seed] = result  # the run in the main table
                continue
            seeded = method_cfg.copy()
            seeded.crop.seed = seed
            relocalizer.crop = build(seeded, "crop", choices["crop"])
            runs[seed] = evaluate(f"{result.method}, crop.seed={seed}", relocalizer, *test, quiet)
    finally:
        relocalizer.crop = configured
    return runs
