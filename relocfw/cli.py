"""`relocfw`: the Hydra command line. The only module that sees a DictConfig."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import torch
from hydra import compose
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException, InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from relocfw import __version__, jobs
from relocfw.compare_job import MapView, write_comparison
from relocfw.distributed import World
from relocfw.errors import ConfigError, RelocfwError
from relocfw.hydra_plugins import install as install_plugin_discovery
from relocfw.hydra_plugins import options_help
from relocfw.interfaces import Backbone, CropSearch, SimilarityIndex
from relocfw.localize_job import find_images, localize_images
from relocfw.model_file import save_model
from relocfw.options import integer_at_least
from relocfw.pipeline import Relocalizer, check_retrieval, check_scoring
from relocfw.plugin_discovery import conflicts, discover_options, source_of
from relocfw.torchrun import join_torchrun, leave_torchrun
from relocfw.training import TrainSettings

TASKS = ("relocalize", "train", "compare", "localize", "plugins")
INTERFACES = {"backbone": Backbone, "index": SimilarityIndex, "crop": CropSearch}


def build(cfg: DictConfig, group: str, choice: str) -> Any:
    """Instantiate the option chosen for `group`, turning failures into one message.

    A plugin's failure names its distribution; an object that is not the group's
    interface names the methods it lacks, before any training starts.
    """
    source = source_of(group, choice)
    where = f"{group}={choice}"
    if source is not None and source.distribution != "relocfw":
        where += f" (from {source.distribution})"
    try:
        obj = instantiate(cfg[group])
    except InstantiationException as error:
        cause = error.__cause__ or error
        if isinstance(cause, RelocfwError):
            raise ConfigError(f"{where}: {cause}") from error
        raise ConfigError(f"{where}: {type(cause).__name__}: {cause}") from error
    except OmegaConfBaseException as error:
        raise ConfigError(f"{where}: {error}") from error
    expected = INTERFACES.get(group)
    if expected is not None and not isinstance(obj, expected):
        missing = sorted(
            name for name in expected.__abstractmethods__ if not callable(getattr(obj, name, None))
        )
        lacks = f"; it lacks {', '.join(missing)}" if missing else ""
        raise ConfigError(
            f"{where}: {type(obj).__module__}.{type(obj).__qualname__} does not implement "
            f"relocfw.{expected.__name__} (subclass it){lacks}"
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


@dataclass
class Method:
    """Everything one configured method needs, built and checked."""

    label: str
    backbone: Backbone
    index: SimilarityIndex
    crop: CropSearch
    retrieval_k: int
    settings: TrainSettings
    identity: dict[str, Any]
    options: dict[str, dict[str, Any]]

    scoring: str

    def relocalizer(self, device: torch.device, batch_size: int) -> Relocalizer:
        return Relocalizer(
            self.backbone,
            self.index,
            self.crop,
            device,
            batch_size,
            self.retrieval_k,
            self.scoring,
        )


def method_label(cfg: DictConfig, choices: Mapping[str, str]) -> str:
    label = f"{choices['crop']} + {choices['index']}"
    if choices["index"] == "kmeans":
        label += f" (k={cfg.index.k})"
    if int(cfg.retrieval_k) > 0:
        label = f"retrieval of {cfg.retrieval_k} nearest, {choices['crop']} crop"
    if cfg.scoring != "plain":
        label += f", {cfg.scoring} scoring"
    if choices["backbone"] != "posenet" or int(cfg.backbone.get("mc_samples", 0)) > 0:
        samples = int(cfg.backbone.get("mc_samples", 0))
        label = f"{choices['backbone']}{f' x{samples} MC' if samples else ''}: {label}"
    return label


def build_method(cfg: DictConfig, choices: Mapping[str, str], label: str | None = None) -> Method:
    """Build and check every plugin before any slow work, so a bad option fails fast."""
    settings = train_settings(cfg)
    retrieval_k = integer_at_least("retrieval_k", cfg.retrieval_k, 0)
    # Seeded here, in the CLI, so the same command initialises the same network.
    torch.manual_seed(int(cfg.seed))
    backbone = build(cfg, "backbone", choices["backbone"])
    index = build(cfg, "index", choices["index"])
    crop = build(cfg, "crop", choices["crop"])
    check_retrieval(index, retrieval_k)
    check_scoring(str(cfg.scoring), backbone)
    options = {
        group: {
            k: v
            for k, v in OmegaConf.to_container(cfg[group], resolve=True).items()
            if k != "_target_"
        }
        for group in ("backbone", "index", "crop")
    }
    identity = {
        "dataset": dataset_settings(cfg),
        "backbone": {
            k: v for k, v in options["backbone"].items() if k not in backbone.test_time_options
        },
    }
    return Method(
        label or method_label(cfg, choices),
        backbone,
        index,
        crop,
        retrieval_k,
        settings,
        identity,
        options,
        str(cfg.scoring),
    )


def dataset_settings(cfg: DictConfig) -> dict[str, Any]:
    """What identifies the data: the dataset options without where caches live."""
    values = OmegaConf.to_container(cfg.dataset, resolve=True)
    return {k: v for k, v in values.items() if k not in ("cache_dir", "quiet")}


def check_common(cfg: DictConfig) -> torch.device:
    if cfg.task not in TASKS:
        raise ConfigError(f"task must be one of {', '.join(TASKS)}, got {cfg.task!r}")
    unknown = set(cfg.baselines) - set(jobs.BASELINES)
    if unknown:
        raise ConfigError(f"baselines: unknown {sorted(unknown)}; known: {list(jobs.BASELINES)}")
    integer_at_least("query_batch_size", cfg.query_batch_size, 1)
    return pick_device(cfg.device)


def prepare_model(
    cfg: DictConfig,
    method: Method,
    train: tuple,
    device: torch.device,
    world: World | None = None,
) -> Path:
    checkpoint, training = jobs.train_or_reuse(
        method.backbone,
        *train,
        method.settings,
        method.identity,
        Path(cfg.cache_dir),
        device,
        bool(cfg.quiet),
        world,
    )
    if world is not None and not world.is_main:
        return checkpoint
    if training.reused:
        how = "reused"
    elif training.resumed_from:
        how = f"trained, resumed from step {training.resumed_from}"
    else:
        how = "trained"
    print(f"model: {checkpoint} ({how})")
    return checkpoint


def run_localize(cfg: DictConfig, device: torch.device) -> None:
    if not cfg.model:
        raise ConfigError("model is not set: pass model=FILE (a model.relocfw from a run)")
    relocalizer = Relocalizer.load(
        Path(cfg.model), device, int(cfg.query_batch_size), str(cfg.scoring)
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
    train = jobs.load_split(dataset, "train", quiet or (world is not None and not world.is_main))
    if world is not None and world.is_main:
        world.barrier()
    if cfg.task == "relocalize":
        method.index.check_map_size(len(train[0]))
    checkpoint = prepare_model(cfg, method, train, device, world)
    if cfg.task == "train":
        jobs.write_skipped(dataset, run_dir)
        return
    test = jobs.load_split(dataset, "test", quiet)
    jobs.write_skipped(dataset, run_dir)
    relocalizer = method.relocalizer(device, int(cfg.query_batch_size))
    jobs.relocalize(
        relocalizer,
        method.label,
        train,
        test,
        run_dir,
        baselines=list(cfg.baselines),
        centre_label=f"{choices['backbone']} (centre crop)",
        quiet=quiet,
    )
    metadata = {
        "method": method.label,
        "dataset": choices["dataset"],
        "dataset_settings": dataset_settings(cfg),
        "map_images": len(train[0]),
        "checkpoint": str(checkpoint),
        "relocfw_version": __version__,
    }
    model = save_model(run_dir / "model.relocfw", relocalizer, method.options, metadata)
    print(f"model file: {model}  (relocfw task=localize model={model} images=...)")


def compose_method(overrides: list[str], name: str) -> tuple[DictConfig, Mapping[str, str]]:
    try:
        cfg = compose(config_name="config", overrides=overrides, return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as error:
        raise ConfigError(f"compare.methods.{name}: {error}") from error
    return cfg, cfg.hydra.runtime.choices


def run_compare(cfg: DictConfig, device: torch.device) -> None:
    """Every method of compare.methods on every scene; each model trained once."""
    methods = OmegaConf.to_container(cfg.compare.methods, resolve=True)
    if not methods:
        raise ConfigError("compare.methods is empty")
    scenes = list(cfg.compare.scenes or [None])
    reference = str(cfg.compare.reference)
    if reference not in methods:
        raise ConfigError(f"compare.reference={reference!r} is not in compare.methods")
    base = [o for o in HydraConfig.get().overrides.task if not o.startswith(("task=", "compare."))]
    quiet = bool(cfg.quiet)
    # Compose and build every method first: a typo fails before hours of training.
    plans = {}
    for scene in scenes:
        scene_override = [f"dataset.scene={scene}"] if scene is not None else []
        for name, overrides in methods.items():
            method_cfg, choices = compose_method(base + scene_override + list(overrides), name)
            plans[scene, name] = (method_cfg, choices)
    results, training, maps = {}, {}, {}
    for scene in scenes:
        first_cfg, first_choices = plans[scene, next(iter(methods))]
        dataset = build(first_cfg, "dataset", first_choices["dataset"])
        label = scene or first_choices["dataset"]
        train = jobs.load_split(dataset, "train", quiet)
        test = jobs.load_split(dataset, "test", quiet)
        jobs.write_skipped(dataset, Path(HydraConfig.get().runtime.output_dir))
        results[label], training[label], maps[label] = {}, train[0], None
        for name in methods:
            method_cfg, choices = plans[scene, name]
            method = build_method(method_cfg, choices, label=name)
            method.index.check_map_size(len(train[0]))
            prepare_model(method_cfg, method, train, device)
            relocalizer = method.relocalizer(device, int(cfg.query_batch_size))
            result, features = jobs.run_method(name, relocalizer, train, test, quiet)
            results[label][name] = result
            if maps[label] is None and hasattr(method.index, "centres"):
                standardised = method.index.zscore(features)
                labels = method.index.assign(features)
                maps[label] = MapView(standardised, method.index.centres, labels)
    write_comparison(
        results,
        training,
        maps,
        reference,
        Path(HydraConfig.get().runtime.output_dir),
        seed=int(cfg.seed),
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
    install_plugin_discovery()
    clashes = conflicts(discover_options())
    for line in clashes:
        print(f"warning: {line}", file=sys.stderr)
    hydra_main()


if __name__ == "__main__":
    main()
