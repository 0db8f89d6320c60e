"""The CLI's method building: a composed config in, checked plugin instances out."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from relocfw.app import relocalize_task
from relocfw.app.compare_task import safe_name
from relocfw.app.plugin_discovery import source_of
from relocfw.core.errors import ConfigError, RelocfwError
from relocfw.core.interfaces import Backbone, CropSearch, SimilarityIndex
from relocfw.core.options import integer_at_least
from relocfw.core.pipeline import (
    Relocalizer,
    check_rerank,
    check_retrieval,
    check_sampling,
    check_scoring,
)
from relocfw.core.sampling import configured_samples
from relocfw.model.distributed import World
from relocfw.model.training import TrainSettings
from relocfw.report.figures import training_curve
from relocfw.report.units import METRES, PositionUnit

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
    values.pop("log", None)  # where curves go, not how the model trains: not in the key
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
    """The torch device that `device=` names, checked to exist on this machine.

    Checked before any data is read or model built: a device that is not there would
    otherwise fail deep inside torch, with a traceback, after minutes of work.

    Raises:
        ConfigError: naming `device`, for a malformed name, a missing CUDA or MPS, or
            a CUDA index beyond the devices this machine has.
    """
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as error:  # TypeError: device=null
        raise ConfigError(
            f"device={name} is not a device name; use cpu, cuda, cuda:N or mps"
        ) from error
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device={name}, but CUDA is not available here; use device=cpu")
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise ConfigError(
                f"device={name}, but this machine has {count} CUDA device(s): "
                f"use cuda:0 to cuda:{count - 1}"
            )
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise ConfigError(f"device={name}, but MPS is not available here; use device=cpu")
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
    crop_samples: int = 0
    sample_seed: int = 0
    rerank: int = 1
    queries_at_once: int = 1

    def relocalizer(self, device: torch.device, batch_size: int) -> Relocalizer:
        return Relocalizer(
            self.backbone,
            self.index,
            self.crop,
            device,
            batch_size,
            self.retrieval_k,
            self.scoring,
            crop_samples=self.crop_samples,
            sample_seed=self.sample_seed,
            rerank=self.rerank,
            queries_at_once=self.queries_at_once,
        )


def method_label(cfg: DictConfig, choices: Mapping[str, str]) -> str:
    label = f"{choices['crop']} + {choices['index']}"
    if choices["index"] == "kmeans":
        label += f" (k={cfg.index.k})"
    if int(cfg.retrieval_k) > 0:
        label = f"retrieval of {cfg.retrieval_k} nearest, {choices['crop']} crop"
    if cfg.scoring != "plain":
        label += f", {cfg.scoring} scoring"
    if int(cfg.get("rerank", 1)) > 1:
        label += f", best {cfg.rerank} re-scored"
    crops = int(cfg.get("crop_samples", 0))
    samples = int(cfg.backbone.get("mc_samples", 0))
    if crops > 0:
        label += f", x{crops} random crops"
    if choices["backbone"] != "posenet" or samples > 0:
        variant = cfg.backbone.get("dropout_variant")
        where = f" ({variant})" if variant else ""
        # With random crops, dropout draws one mask per crop: the count is the crops'.
        sampled = (f" MC dropout{where}" if crops else f" x{samples} MC{where}") if samples else ""
        label = f"{choices['backbone']}{sampled}: {label}"
    return label


def centre_label(cfg: DictConfig, choices: Mapping[str, str]) -> str:
    """The centre-crop baseline's row name; it says so when dropout is sampled."""
    samples = int(cfg.backbone.get("mc_samples", 0))
    sampled = f" x{samples} MC dropout" if samples else ""
    return f"{choices['backbone']}{sampled} (centre crop)"


def build_method(cfg: DictConfig, choices: Mapping[str, str], label: str | None = None) -> Method:
    """Build and check every plugin before any slow work, so a bad option fails fast."""
    settings = train_settings(cfg)
    retrieval_k = integer_at_least("retrieval_k", cfg.retrieval_k, 0)
    crop_samples = integer_at_least("crop_samples", cfg.get("crop_samples", 0), 0)
    # Seeded here, in the CLI, so the same command initialises the same network.
    torch.manual_seed(int(cfg.seed))
    backbone = build(cfg, "backbone", choices["backbone"])
    index = build(cfg, "index", choices["index"])
    crop = build(cfg, "crop", choices["crop"])
    check_retrieval(index, retrieval_k)
    check_scoring(str(cfg.scoring), backbone)
    rerank = check_rerank(integer_at_least("rerank", cfg.get("rerank", 1), 1), str(cfg.scoring))
    # Before training: the trained model will have train.crop_scale.
    check_sampling(retrieval_k, crop_samples, configured_samples(backbone), settings.crop_scale)
    check_pretrained(cfg, choices, backbone)
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
            k: v
            for k, v in options["backbone"].items()
            if k not in backbone.test_time_options
            and not (k in backbone.key_defaults and backbone.key_defaults[k] == v)
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
        crop_samples,
        int(cfg.seed),
        rerank,
        integer_at_least("queries_at_once", cfg.get("queries_at_once", 1), 1),
    )


def check_pretrained(cfg: DictConfig, choices: Mapping[str, str], backbone: Backbone) -> None:
    """Refuse fine-tuning settings for a network that starts from random weights.

    The paper fine-tunes ImageNet GoogLeNet at lr 1e-5; from random initialisation that
    rate does not learn in any reasonable number of steps.
    """
    if not cfg.get("pretrained_required", False) or backbone.pretrained:
        return
    preset = choices.get("preset", "?")
    raise ConfigError(
        f"preset={preset} fine-tunes ImageNet weights (train.lr={cfg.train.lr}) and cannot "
        f"train backbone={choices['backbone']} from random initialisation: give "
        "backbone.weights=FILE (a torchvision GoogLeNet state_dict, see the README's "
        "'ImageNet weights'), or a pretrained backbone (backbone=efficientnet_lite0 with "
        "backbone.pretrained=true), "
        "or train from scratch with preset=demo (pretrained_required=false trains anyway)"
    )


def dataset_settings(cfg: DictConfig) -> dict[str, Any]:
    """What identifies the data: the dataset options without where caches live."""
    values = OmegaConf.to_container(cfg.dataset, resolve=True)
    # metric only names the unit of the reports: the same poses train the same model.
    return {k: v for k, v in values.items() if k not in ("cache_dir", "quiet", "metric")}


def prepare_model(
    cfg: DictConfig,
    method: Method,
    train: tuple,
    device: torch.device,
    world: World | None = None,
    curve: Path | None = None,
    curve_dir: Path | None = None,
    unit: PositionUnit = METRES,
) -> Path:
    """Train the method's network or reuse its checkpoint; print which.

    Args:
        curve: where to draw the run's training curve (from the checkpoint's history
            when it is reused). With train.log=tensorboard, the events of a run that
            trains go to a `tensorboard/` folder beside it.
        curve_dir: instead of `curve`, a folder: the curve is then
            `training_curve_<checkpoint>.png` there, one file per distinct model.
        unit: what the curve's position errors are in (the dataset's unit).
    """
    log = str(cfg.train.get("log", "none"))
    if log not in ("none", "tensorboard"):
        raise ConfigError(f"train.log must be none or tensorboard, got {log!r}")
    log_dir = None
    if log == "tensorboard" and curve is not None:
        log_dir = curve.parent / "tensorboard"
    elif log == "tensorboard" and curve_dir is not None:  # several models: one run each
        log_dir = curve_dir / "tensorboard" / safe_name(method.label)
    checkpoint, training = relocalize_task.train_or_reuse(
        method.backbone,
        *train,
        method.settings,
        method.identity,
        Path(cfg.cache_dir),
        device,
        bool(cfg.quiet),
        world,
        log_dir,
    )
    if world is not None and not world.is_main:
        return checkpoint
    if curve is None and curve_dir is not None:
        curve = curve_dir / f"training_curve_{checkpoint.stem}.png"
    if curve is not None:
        history = training.history or {"loss": training.losses}  # an older checkpoint
        training_curve(history, curve, f"({checkpoint.name})", unit)
    if training.reused:
        how = "reused"
    elif training.resumed_from:
        how = f"trained, resumed from step {training.resumed_from}"
    else:
        how = "trained"
    print(f"model: {checkpoint} ({how})")
    return checkpoint
