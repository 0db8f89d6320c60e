"""What the service answers, as JSON: one Localization (POST /v1/localize) and the
model it runs (GET /v1/model).

JSON has no NaN or infinity: a number that is not finite is null (an unknown value, a
bound the model does not have, or an infinite one: too few validation answers like
this one to bound it).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relocfw.core.pipeline import Relocalizer
from relocfw.core.sampling import configured_samples
from relocfw.core.values import Localization
from relocfw.core.version import VERSION

# Datasets whose poses are in metres; a COLMAP model's scale is its own.
METRIC_DATASETS = frozenset({"synthetic", "sevenscenes", "cambridge", "tum", "rosbag", "folder"})
QUATERNION_ORDER = "wxyz"
POSE_FRAME = "camera_to_world"
# The uncertainty signal an answer carries (the names of relocfw.core.trust_signal).
CONFIDENCE = "refiner confidence"
SPREAD = "spread"
NO_SIGNAL = "none"


def finite_or_none(value: Any) -> float | None:
    number = float(value)
    return number if math.isfinite(number) else None


def file_id(path: Path) -> str:
    """The model's id: the first 16 hex digits of the file's SHA-256, so an answer
    names the exact file that made it."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def part_name(part: object) -> str | None:
    return None if part is None else type(part).__name__


@dataclass(frozen=True)
class ModelInfo:
    """What GET /v1/model says, and what every answer repeats (id, units, coverage)."""

    model_id: str
    file_name: str
    backbone: str
    input_size: int | None
    crop_search: str
    refiner: str | None
    index: str
    map_size: int
    units: str
    signal: str
    coverage: float | None
    scoring: str
    metadata: Mapping[str, Any]

    def as_json(self) -> dict[str, Any]:
        return {
            "model_id": self.model_id,
            "file_name": self.file_name,
            "backbone": self.backbone,
            "input_size": self.input_size,
            "crop_search": self.crop_search,
            "refiner": self.refiner,
            "index": self.index,
            "map_size": self.map_size,
            "units": self.units,
            "uncertainty_signal": self.signal,
            "error_bounds_coverage": self.coverage,
            "scoring": self.scoring,
            "method": self.metadata.get("method"),
            "dataset": self.metadata.get("dataset"),
            "scene": self.metadata.get("scene"),
            "trained_with_relocfw": self.metadata.get("relocfw_version"),
            "relocfw_version": VERSION,
        }


def units_of(metadata: Mapping[str, Any]) -> str:
    """ "m" where the model's dataset is metric, else "map units" (the map's own scale)."""
    stated = metadata.get("units")
    if isinstance(stated, str) and stated:
        return stated
    return "m" if metadata.get("dataset") in METRIC_DATASETS else "map units"


def signal_of(relocalizer: Relocalizer) -> str:
    """The uncertainty signal the model's answers carry: the refiner's confidence with a
    refiner, the samples' spread where the model samples, else none."""
    if getattr(relocalizer, "refiner", None) is not None:
        return CONFIDENCE
    options = relocalizer.options
    samples = configured_samples(relocalizer.backbone)
    return SPREAD if options.crop_samples > 0 or samples > 0 else NO_SIGNAL


def describe_model(relocalizer: Relocalizer, path: Path) -> ModelInfo:
    """ModelInfo of a loaded model file."""
    metadata = dict(getattr(relocalizer, "metadata", {}) or {})
    bounds = getattr(relocalizer, "bounds", None)
    coverage = None if bounds is None else finite_or_none(getattr(bounds, "coverage", math.nan))
    map_size = len(relocalizer.map_poses) or int(metadata.get("map_images", 0) or 0)
    input_size = getattr(relocalizer.backbone, "input_size", None)
    return ModelInfo(
        model_id=file_id(path),
        file_name=Path(path).name,
        backbone=type(relocalizer.backbone).__name__,
        input_size=int(input_size) if isinstance(input_size, int) else None,
        crop_search=type(relocalizer.search).__name__,
        refiner=part_name(getattr(relocalizer, "refiner", None)),
        index=type(relocalizer.index).__name__,
        map_size=map_size,
        units=units_of(metadata),
        signal=signal_of(relocalizer),
        coverage=coverage,
        scoring=relocalizer.options.scoring,
        metadata=metadata,
    )


def uncertainty_value(answer: Localization, signal: str) -> float | None:
    if signal == CONFIDENCE:
        return finite_or_none(answer.refine_confidence)
    if signal == SPREAD:
        return finite_or_none(answer.position_spread)
    return None


def error_bounds(answer: Localization, coverage: float | None) -> dict[str, Any] | None:
    """The calibrated bounds (null where the model has none: both NaN)."""
    position = float(getattr(answer, "position_bound", math.nan))
    orientation = float(getattr(answer, "orientation_bound_deg", math.nan))
    if math.isnan(position) and math.isnan(orientation):
        return None
    return {
        "position": finite_or_none(position),
        "orientation_deg": finite_or_none(orientation),
        "coverage": coverage,
    }


@dataclass(frozen=True)
class Timings:
    """A request's milliseconds: reading and decoding the body, waiting for a worker,
    the pipeline's own time (with the refiner's parts), and all of it."""

    decode_ms: float
    queue_ms: float
    total_ms: float


def answer_json(
    answer: Localization, info: ModelInfo, timings: Timings, name: str | None
) -> dict[str, Any]:
    """The JSON of one answer (the fields docs/serve.md lists)."""
    localize_ms = 1000.0 * answer.seconds
    stages = {f"refine_{part}": 1000.0 * s for part, s in answer.refine_seconds.items()}
    position, quaternion = answer.pose.position, answer.pose.quaternion
    return {
        "position": [float(v) for v in position],
        "quaternion": [float(v) for v in quaternion],
        "quaternion_order": QUATERNION_ORDER,
        "pose": POSE_FRAME,
        "units": info.units,
        "confidence": finite_or_none(answer.refine_confidence),
        "error_bounds": error_bounds(answer, info.coverage),
        "fell_back": bool(answer.fell_back),
        "uncertainty": {
            "name": info.signal,
            "value": uncertainty_value(answer, info.signal),
            "position_spread": finite_or_none(answer.position_spread),
            "orientation_spread_deg": finite_or_none(answer.orientation_spread_deg),
        },
        "crop": {"x": answer.crop.x, "y": answer.crop.y, "size": answer.crop.size},
        "distance": finite_or_none(answer.distance),
        "crops_scored": int(answer.evaluations),
        "ms": {
            "decode": timings.decode_ms,
            "queue": max(0.0, timings.queue_ms - localize_ms),
            "localize": localize_ms,
            **stages,
            "total": timings.total_ms,
        },
        "model_id": info.model_id,
        "name": name,
    }
