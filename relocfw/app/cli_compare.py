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

from relocfw.app import relocalize_task
from relocfw.app.cli_methods import build, build_method, prepare_model
from relocfw.app.compare_task import MapView, write_comparison, write_seed_comparison
from relocfw.core.errors import ConfigError
from relocfw.core.options import integer_at_least
from relocfw.core.pipeline import Relocalizer
from relocfw.data.frames import mean_pose
from relocfw.report.evaluation import MethodResult, constant_answer, evaluate
from relocfw.report.units import PositionUnit, unit_of


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


def training_seeds(cfg: DictConfig) -> list[int]:
    """compare.seeds, or the run's own seed when unset."""
    if cfg.compare.get("seeds") is None:
        return [int(cfg.seed)]
    if not OmegaConf.is_list(cfg.compare.seeds):
        raise ConfigError(f"compare.seeds must be a list such as [0,1,2], got {cfg.compare.seeds}")
    seeds = list(cfg.compare.seeds)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ConfigError(f"compare.seeds must be distinct integers, got {seeds}")
    return [integer_at_least("compare.seeds", s, 0) for s in seeds]


def run_compare(cfg: DictConfig, device: torch.device) -> None:
    """Every method of compare.methods on every scene, for every training seed.

    Each (seed, scene, method) model is trained once (or found in the cache); with
    several seeds, each seed's full comparison goes to seed_<n>/ and the top-level
    comparison files hold the spread over seeds and the paired tests.
    """
    methods = OmegaConf.to_container(cfg.compare.methods, resolve=True)
    if not methods:
        raise ConfigError("compare.methods is empty")
    scenes = list(cfg.compare.scenes or [None])
    reference = str(cfg.compare.reference)
    if reference not in methods:
        raise ConfigError(f"compare.reference={reference!r} is not in compare.methods")
    seeds = training_seeds(cfg)
    base = [
        o
        for o in HydraConfig.get().overrides.task
        if not o.lstrip("~+").startswith(("task=", "compare."))
    ]
    quiet = bool(cfg.quiet)
    crop_seeds = [int(s) for s in cfg.compare.crop_seeds or []]
    # Compose and build every method first: a typo fails before hours of training.
    plans, rows = {}, {}
    for seed in seeds:
        for scene in scenes:
            scene_override = [f"dataset.scene={scene}"] if scene is not None else []
            for name, overrides in methods.items():
                composed = base + scene_override + list(overrides) + [f"seed={seed}"]
                method_cfg, choices = compose_method(composed, name)
                if len(seeds) > 1 and int(method_cfg.train.seed) != seed:
                    # train.seed=N on the command line would pin every "seed" to one
                    # model: a spread of zero and a meaningless test.
                    raise ConfigError(
                        f"compare.seeds: train.seed is pinned to {method_cfg.train.seed}; "
                        "drop train.seed= so each training seed trains its own model"
                    )
                plans[seed, scene, name] = (method_cfg, choices)
                rows[name] = row_label(name, list(overrides), method_cfg)
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    results = {seed: {} for seed in seeds}
    seed_runs = {seed: {} for seed in seeds}
    maps = {seed: {} for seed in seeds}
    training, floors = {}, {}
    units: dict[str, PositionUnit] = {}
    for scene in scenes:
        first_cfg, first_choices = plans[seeds[0], scene, next(iter(methods))]
        dataset = build(first_cfg, "dataset", first_choices["dataset"])
        label = scene or first_choices["dataset"]
        units[label] = unit_of(dataset)
        unit = one_unit(units)  # a mixed list fails before this scene trains
        train = relocalize_task.load_split(dataset, "train", quiet)
        test = relocalize_task.load_split(dataset, "test", quiet)
        relocalize_task.write_skipped(dataset, run_dir)
        training[label] = train[0]
        floors[label] = constant_answer("mean training pose", mean_pose(train[0]), test[0])
        for seed in seeds:
            if len(seeds) > 1:
                print(f"\n== {label}: training seed {seed} ==")
            results[seed][label], seed_runs[seed][label] = {}, {}
            maps[seed][label] = None
            for name in methods:
                method_cfg, choices = plans[seed, scene, name]
                method = build_method(method_cfg, choices, label=rows[name])
                method.index.check_map_size(len(train[0]))
                # One curve per distinct model: rows sharing a model share its file.
                seed_dir = run_dir / f"seed_{seed}" if len(seeds) > 1 else run_dir
                prepare_model(
                    method_cfg, method, train, device, curve_dir=seed_dir, unit=unit_of(dataset)
                )
                relocalizer = method.relocalizer(device, int(cfg.query_batch_size))
                result, features = relocalize_task.run_method(
                    rows[name], relocalizer, train, test, quiet
                )
                results[seed][label][rows[name]] = result
                if "seed" in method_cfg.crop and len(crop_seeds) > 1:
                    seed_runs[seed][label][rows[name]] = rerun_crop_seeds(
                        method_cfg, choices, relocalizer, result, test, crop_seeds, quiet
                    )
                if maps[seed][label] is None and hasattr(method.index, "centres"):
                    standardised = method.index.zscore(features)
                    labels = method.index.assign(features)
                    maps[seed][label] = MapView(standardised, method.index.centres, labels)
    for seed in seeds:
        write_comparison(
            results[seed],
            training,
            maps[seed],
            rows[reference],
            run_dir / f"seed_{seed}" if len(seeds) > 1 else run_dir,
            seed=seed,
            seed_runs=seed_runs[seed],
            unit=unit,
        )
    if len(seeds) > 1:
        write_seed_comparison(
            results, floors, rows[reference], run_dir, bootstrap_seed=seeds[0], unit=unit
        )
    if unit.note:
        print(f"note: {unit.note}")


def one_unit(units: Mapping[str, PositionUnit]) -> PositionUnit:
    """The positions' unit shared by every scene: one table cannot mix metres with
    model units (its average row would add them)."""
    if len({unit.metric for unit in units.values()}) > 1:
        named = ", ".join(f"{scene}: {unit.name}" for scene, unit in units.items())
        raise ConfigError(f"compare.scenes measure positions in different units ({named})")
    return next(iter(units.values()))


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
