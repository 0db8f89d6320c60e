"""The tasks' method building: a composed config in, checked plugin instances out."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from relocfw.app.plugin_discovery import source_of
from relocfw.core.errors import ConfigError, RelocfwError
from relocfw.core.interfaces import Backbone, CropSearch, SimilarityIndex
from relocfw.core.pipeline import Relocalizer, check_options
from relocfw.core.query_options import QueryOptions
from relocfw.core.refinement import PoseRefiner
from relocfw.model.training import TrainSettings

INTERFACES = {
    "backbone": Backbone,
    "index": SimilarityIndex,
    "crop": CropSearch,
    "refine": PoseRefiner,
}
# Methods of which an interface needs one, not all (not abstract, so not listed by
# __abstractmethods__): a CropSearch defines propose or the older search.
ONE_OF = {CropSearch: ("propose", "search")}
# Keys of the train: group that do not say how the model trains, so not in its key:
# where curves go, and a guard on the backbone's starting weights.
NOT_TRAINING = ("log", "pretrained_required")
QUERY_FIELDS = tuple(f.name for f in dataclasses.fields(QueryOptions))


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
        either = ONE_OF.get(expected, ())
        if either and not any(callable(getattr(obj, name, None)) for name in either):
            missing.append(" or ".join(either))
        lacks = f"; it lacks {', '.join(missing)}" if missing else ""
        raise ConfigError(
            f"{where}: {type(obj).__module__}.{type(obj).__qualname__} does not implement "
            f"relocfw.{expected.__name__} (subclass it){lacks}"
        )
    return obj


def train_settings(cfg: DictConfig) -> TrainSettings:
    values = OmegaConf.to_container(cfg.train, resolve=True, enum_to_str=True)
    for key in NOT_TRAINING:
        values.pop(key, None)
    try:
        for key in ("auxiliary_weights", "learned_init"):
            if key in values:
                values[key] = tuple(values[key])
        settings = TrainSettings(**values)
    except TypeError as error:
        raise ConfigError(f"train: {error}") from error
    settings.validate()
    return settings


def query_values(cfg: DictConfig) -> dict[str, Any]:
    """The query: group as plain values; None where the config leaves one unset."""
    return OmegaConf.to_container(cfg.query, resolve=True, enum_to_str=True)


def in_query_terms(error: ConfigError) -> ConfigError:
    """QueryOptions names its fields bare (`rerank=3 ...`); the config spells them
    `query.rerank`, so the message names the key a user typed."""
    text = str(error)
    if text.replace("=", " ").split(" ", 1)[0] in QUERY_FIELDS:
        return ConfigError(f"query.{text}")
    return error


def query_options(cfg: DictConfig) -> QueryOptions:
    """The run's QueryOptions: each query.* value, its default where null (the sample
    seed's default is the run's seed)."""
    values = query_values(cfg)
    if values.get("sample_seed") is None:
        values["sample_seed"] = int(cfg.seed)
    try:
        return QueryOptions.from_mapping(values, where="query")
    except ConfigError as error:
        raise in_query_terms(error) from error


@dataclass
class Method:
    """Everything one configured method needs, built and checked."""

    label: str
    backbone: Backbone
    index: SimilarityIndex
    search: CropSearch
    query: QueryOptions
    settings: TrainSettings
    identity: dict[str, Any]
    part_options: dict[str, dict[str, Any]]  # what the parts were built with
    refiner: PoseRefiner | None = None  # refine=none: the network's pose

    def relocalizer(self, device: torch.device) -> Relocalizer:
        return Relocalizer(self.backbone, self.index, self.search, self.query, device, self.refiner)


def method_label(cfg: DictConfig, choices: Mapping[str, str], query: QueryOptions) -> str:
    label = f"{choices['crop']} + {choices['index']}"
    if choices["index"] == "kmeans":
        label += f" (k={cfg.index.k})"
    refine = choices.get("refine", "none")
    if refine == "retrieval":
        # The crop search chooses the query's descriptor (the centre crop needs no
        # index); the map images nearest to it answer the pose.
        search = choices["crop"] if choices["crop"] == "centre" else label
        label = f"retrieval of {int(cfg.refine.get('k', 1))} nearest, {search} crop"
    if query.scoring != "plain":
        label += f", {query.scoring} scoring"
    if query.rerank > 1:
        label += f", best {query.rerank} re-scored"
    crops = query.crop_samples
    samples = int(cfg.backbone.get("mc_samples", 0))
    if crops > 0:
        label += f", x{crops} random crops"
    if choices["backbone"] != "posenet" or samples > 0:
        variant = cfg.backbone.get("dropout_variant")
        where = f" ({variant})" if variant else ""
        # With random crops, dropout draws one mask per crop: the count is the crops'.
        sampled = (f" MC dropout{where}" if crops else f" x{samples} MC{where}") if samples else ""
        label = f"{choices['backbone']}{sampled}: {label}"
    if refine not in ("none", "retrieval"):
        label += f" + {refine}"
    return label


def centre_label(cfg: DictConfig, choices: Mapping[str, str]) -> str:
    """The centre-crop baseline's row name; it says so when dropout is sampled."""
    samples = int(cfg.backbone.get("mc_samples", 0))
    sampled = f" x{samples} MC dropout" if samples else ""
    return f"{choices['backbone']}{sampled} (centre crop)"


def scene_name(cfg: DictConfig, choices: Mapping[str, str]) -> str:
    """What reports call the data: the dataset's scene where it has one (`redkitchen`),
    else the loader's name (`synthetic`, `colmap`)."""
    return str(cfg.dataset.get("scene") or choices["dataset"])


def build_method(cfg: DictConfig, choices: Mapping[str, str], label: str | None = None) -> Method:
    """Build and check every plugin before any slow work, so a bad option fails fast."""
    settings = train_settings(cfg)
    query = query_options(cfg)
    # Seeded here, in the CLI, so the same command initialises the same network.
    torch.manual_seed(int(cfg.seed))
    backbone = build(cfg, "backbone", choices["backbone"])
    index = build(cfg, "index", choices["index"])
    search = build(cfg, "crop", choices["crop"])
    refine = choices.get("refine", "none")
    refiner = None if refine == "none" else build(cfg, "refine", refine)
    # Before training: the trained model will have train.crop_scale.
    try:
        check_options(query, backbone, index, settings.crop_scale, refiner, search)
    except ConfigError as error:
        raise in_query_terms(error) from error
    check_pretrained(cfg, choices, backbone)
    parts = {
        group: {
            k: v
            for k, v in OmegaConf.to_container(cfg[group], resolve=True).items()
            if k != "_target_"
        }
        for group in ("backbone", "index", "crop", "refine")
        if group != "refine" or refiner is not None
    }
    identity = {
        "dataset": dataset_settings(cfg),
        "backbone": {
            k: v
            for k, v in parts["backbone"].items()
            if k not in backbone.test_time_options
            and not (k in backbone.key_defaults and backbone.key_defaults[k] == v)
        },
    }
    return Method(
        label or method_label(cfg, choices, query),
        backbone,
        index,
        search,
        query,
        settings,
        identity,
        parts,
        refiner,
    )


def check_pretrained(cfg: DictConfig, choices: Mapping[str, str], backbone: Backbone) -> None:
    """Refuse fine-tuning settings for a network that starts from random weights.

    The paper fine-tunes ImageNet GoogLeNet at lr 1e-5; from random initialisation that
    rate does not learn in any reasonable number of steps.
    """
    if not cfg.train.get("pretrained_required", False) or backbone.pretrained:
        return
    preset = choices.get("preset", "?")
    raise ConfigError(
        f"preset={preset} fine-tunes ImageNet weights (train.lr={cfg.train.lr}) and cannot "
        f"train backbone={choices['backbone']} from random initialisation: give "
        "backbone.weights=FILE (a torchvision GoogLeNet state_dict, see the README's "
        "'ImageNet weights'), or a pretrained backbone (backbone=efficientnet_lite0 with "
        "backbone.pretrained=true), "
        "or train from scratch with preset=demo (train.pretrained_required=false trains anyway)"
    )


def dataset_settings(cfg: DictConfig) -> dict[str, Any]:
    """What identifies the data: the dataset options without where caches live."""
    values = OmegaConf.to_container(cfg.dataset, resolve=True)
    # metric only names the unit of the reports; depth_units_per_metre, intrinsics_for,
    # poses_of and colour_focal only how the structure stage reads depth and cameras and
    # which sensor the poses describe (the network never sees a camera); and a COLMAP
    # model's points only what the structure stage lifts: the same images and poses
    # train the same model.
    left_out = (
        "cache_dir",
        "quiet",
        "metric",
        "depth_units_per_metre",
        "intrinsics_for",
        "poses_of",
        "colour_focal",
        "points",
    )
    return {k: v for k, v in values.items() if k not in left_out}
