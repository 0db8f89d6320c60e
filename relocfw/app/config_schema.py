"""The types of relocfw's configuration, so Hydra refuses a bad value before any work.

conf/config.yaml holds the values and their comments; the dataclasses here hold only
what each value may be (MISSING: the YAML sets it). Composing checks every override
and YAML value against them: `query.batch_size=abc` or `query.scoring=fancy` ends
the command before a scene is rendered or a model built. The plugin groups
(backbone, index, crop, refine, dataset) stay open mappings: their options are the plugins';
so does compare (see RelocfwConfig.compare).

Choices are Enums; `name_of` gives back the plain string the rest of relocfw uses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Dict, List, Optional  # noqa: UP035 (OmegaConf reads these)

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

SCHEMA_NAME = "relocfw_schema"  # the first entry of conf/config.yaml's defaults list


class Task(Enum):
    relocalize = "relocalize"
    train = "train"
    compare = "compare"
    localize = "localize"
    plugins = "plugins"
    diagnose = "diagnose"
    export = "export"
    serve = "serve"
    topics = "topics"


class Scoring(Enum):
    plain = "plain"
    shared = "shared"
    scout = "scout"


class Engine(Enum):
    auto = "auto"
    torch = "torch"
    onnx = "onnx"
    ncnn = "ncnn"


class Int8(Enum):
    none = "none"
    dynamic = "dynamic"
    static = "static"
    static_8bit = "static_8bit"


class Baseline(Enum):
    mean_pose = "mean_pose"
    posenet = "posenet"


class Optimizer(Enum):
    sgd = "sgd"
    adam = "adam"


class LrSchedule(Enum):
    constant = "constant"
    cosine = "cosine"


class Loss(Enum):
    fixed = "fixed"
    learned = "learned"


class PositionFrame(Enum):
    world = "world"
    normalised = "normalised"


class TrainLog(Enum):
    none = "none"
    tensorboard = "tensorboard"


def name_of(value: Any) -> Any:
    """An Enum member's plain string; any other value as it is."""
    return value.value if isinstance(value, Enum) else value


# OmegaConf 2.3 reads typing.Optional/Dict/List, not `X | None` or `dict[...]`, so the
# annotations below keep the old spelling (ruff's UP rules are silenced per line).
@dataclass
class QueryConfig:
    """QueryOptions' fields; None: the model file's value (task=localize) or the default."""

    batch_size: Optional[int] = None  # noqa: UP045
    scoring: Optional[Scoring] = None  # noqa: UP045
    rerank: Optional[int] = None  # noqa: UP045
    crop_samples: Optional[int] = None  # noqa: UP045
    sample_seed: Optional[int] = None  # noqa: UP045
    queries_at_once: Optional[int] = None  # noqa: UP045
    max_aspect: Optional[float] = None  # noqa: UP045
    max_candidates: Optional[int] = None  # noqa: UP045


class OnError(Enum):
    """What task=localize does with a frame that cannot be decoded: stop or list it."""

    fail = "fail"
    skip = "skip"


@dataclass
class LocalizeConfig:
    model: Optional[str] = None  # noqa: UP045
    images: Optional[str] = None  # noqa: UP045
    topic: Optional[str] = None  # noqa: UP045
    on_error: OnError = OnError.fail


@dataclass
class ServeConfig:
    """task=serve (relocfw.serve.settings.ServeSettings checks the values' ranges)."""

    model: Optional[str] = None  # noqa: UP045
    host: str = MISSING
    port: int = MISSING
    workers: int = MISSING
    max_pending: int = MISSING
    max_bytes: int = MISSING
    max_pixels: int = MISSING
    token_file: Optional[str] = None  # noqa: UP045
    retry_after_s: int = MISSING
    header_timeout_s: float = MISSING
    body_timeout_s: float = MISSING
    shutdown_timeout_s: float = MISSING
    max_connections: int = MISSING
    max_connections_per_client: Optional[int] = MISSING  # noqa: UP045


@dataclass
class OnnxConfig:
    threads: Optional[int] = None  # noqa: UP045
    int8: Int8 = Int8.none
    spinning: bool = False


@dataclass
class ExportConfig:
    model: Optional[str] = None  # noqa: UP045
    out: Optional[str] = None  # noqa: UP045


@dataclass
class CalibrateConfig:
    share: float = MISSING
    coverage: float = MISSING
    bins: int = MISSING


@dataclass
class RelocalizeConfig:
    baselines: List[Baseline] = MISSING  # noqa: UP006


@dataclass
class DiagnoseConfig:
    curve_queries: int = MISSING
    table3_queries: int = MISSING


@dataclass
class TrainConfig:
    iterations: int = MISSING
    batch_size: int = MISSING
    optimizer: Optimizer = MISSING
    lr: float = MISSING
    lr_schedule: LrSchedule = MISSING
    momentum: float = MISSING
    weight_decay: float = MISSING
    loss: Loss = MISSING
    beta: float = MISSING
    position_frame: PositionFrame = MISSING
    learned_init: List[float] = MISSING  # noqa: UP006
    auxiliary_weights: List[float] = MISSING  # noqa: UP006
    random_crops: bool = MISSING
    crop_scale: float = MISSING
    checkpoint_every: int = MISSING
    log: TrainLog = MISSING
    seed: int = MISSING
    pretrained_required: bool = MISSING


@dataclass
class RelocfwConfig:
    task: Task = MISSING
    k: int = MISSING
    seed: int = MISSING
    device: str = MISSING
    cache_dir: str = MISSING
    quiet: bool = MISSING
    engine: Engine = MISSING
    onnx: OnnxConfig = field(default_factory=OnnxConfig)
    # The plugin groups: open mappings, their options are the chosen plugin's.
    backbone: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    index: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    crop: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    refine: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    dataset: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    query: QueryConfig = field(default_factory=QueryConfig)
    localize: LocalizeConfig = field(default_factory=LocalizeConfig)
    export: ExportConfig = field(default_factory=ExportConfig)
    serve: ServeConfig = field(default_factory=ServeConfig)
    relocalize: RelocalizeConfig = field(default_factory=RelocalizeConfig)
    calibrate: CalibrateConfig = field(default_factory=CalibrateConfig)
    # Open, and checked where it is read (relocfw.app.tasks.compare): a typed node
    # would refuse `~compare.methods`, the documented way to replace every row.
    compare: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    diagnose: DiagnoseConfig = field(default_factory=DiagnoseConfig)
    train: TrainConfig = field(default_factory=TrainConfig)


def store() -> None:
    """Register the schema with Hydra's ConfigStore (repeatable)."""
    ConfigStore.instance().store(name=SCHEMA_NAME, node=RelocfwConfig)
