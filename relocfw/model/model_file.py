"""One self-describing model file: network, map, crop search, refiner and dataset metadata.

Everything needed to localize new images, loaded without Hydra or the training data:
each part is stored as the import path of its class, the options it was built with
and its state (tensors only, read back with torch's safe weights-only loader).

What a model file may name is limited to registered plugins: torch's weights-only
loader stops code hidden in the pickle, but the loader itself imports the class a
file names and calls it with the file's options, so a file naming e.g. `os.system`
would run a shell command. The class path is therefore checked against the
`_target_`s of the part's config group (relocfw.core.plugin_registry) before
anything is imported, and the imported class must implement the part's interface.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from relocfw.core.error_bounds import ErrorBounds
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.interfaces import Backbone, CropSearch, SimilarityIndex
from relocfw.core.pipeline import Relocalizer
from relocfw.core.plugin_registry import registered_targets
from relocfw.core.query_options import QueryOptions
from relocfw.core.refinement import PoseRefiner
from relocfw.core.trust_signal import CONFIDENCE
from relocfw.model.checkpoints import read_torch_file, save_atomic
from relocfw.model.older_formats import stored_options
from relocfw.model.onnx_backbone import trained_network
from relocfw.model.stored_parts import (
    check_descriptor_dims,
    stored_backbone,
    stored_crop,
    stored_index,
    stored_map_poses,
    stored_metadata,
    stored_refiner,
)

# 2: input normalisation and training crop_scale saved in the state; 3: every query
# option as one QueryOptions mapping ("query"); 4: the refiner ("refine", where it can be
# stored), and retrieval is a refiner, no longer the query option retrieval_k. Format 2
# and 3 files are still read (their retrieval_k as refine=retrieval). A format 3 reader
# must refuse format 4: it would read a retrieval model as the network's pose. 5: the
# refiner's map (refine=features / features_rgb: per map image descriptors, 3-D points,
# cameras; relocfw.structure.map_state), so a loaded model needs no map image; a format 4
# reader must refuse it, or it would answer a structure model with the network's pose
# without saying so. A format 4 file loads as before (it holds no structure refiner).
MODEL_FORMAT = 5
READABLE_FORMATS = (2, 3, 4, 5)
MODEL_KIND = "relocfw-model"
# The parts of a model file: the config group that registers their classes, and the
# interface the class must implement. Every file has the first three; "refine" only
# where the model has a refiner that can be stored (PoseRefiner.saves_state).
PART_INTERFACES: dict[str, type] = {
    "backbone": Backbone,
    "index": SimilarityIndex,
    "crop": CropSearch,
    "refine": PoseRefiner,
}
REQUIRED_PARTS = ("backbone", "index", "crop")
# Query options that change how work is grouped, not the answers (Relocalizer
# .localize_many answers as localize does), and the limits on which queries are taken
# at all (an image past them is refused, never answered otherwise): overriding them
# keeps a file's error bounds.
ANSWER_NEUTRAL_OPTIONS = frozenset(
    {"batch_size", "queries_at_once", "max_aspect", "max_candidates"}
)


def class_path(obj: object) -> str:
    return f"{type(obj).__module__}.{type(obj).__qualname__}"


def registered_class_path(part: object, group: str) -> str:
    """The `_target_` under which `part`'s class is registered in config group `group`.

    Usually its own import path; a YAML may also name the class where its package
    re-exports it, so a target with the same class name is imported and compared
    (the part exists, so its plugin is already imported and trusted).

    Raises:
        ConfigError: the class is registered nowhere: load_model would refuse the file.
    """
    own = class_path(part)
    targets = registered_targets(group)
    if own in targets:
        return own
    name = type(part).__name__
    for target in sorted(t for t in targets if t.rpartition(".")[2] == name):
        module, _, attribute = target.rpartition(".")
        try:
            if getattr(importlib.import_module(module), attribute, None) is type(part):
                return target
        except ImportError:
            continue
    raise ConfigError(
        f"cannot save the {group} {own}: it is not a registered plugin (no {group}/*.yaml "
        "names it as _target_), so load_model would refuse the model file; register it "
        "as docs/plugins.md shows"
    )


def plugin_class(payload: dict[str, Any], group: str, source: Path) -> type:
    """The class a model file names for part `group`, if it is a registered plugin.

    The class path is checked against the registry before it is imported: importing
    a module runs its code, and an unregistered name is refused without running any.
    """
    part = payload.get(group)
    if not isinstance(part, dict):
        raise DataError(f"{source}: damaged model file ({group} is not a mapping)")
    path, options = part.get("class"), part.get("options")
    if not isinstance(path, str):
        raise DataError(f"{source}: damaged model file ({group} class is {path!r}, not a name)")
    if not isinstance(options, dict) or not all(isinstance(key, str) for key in options):
        raise DataError(
            f"{source}: damaged model file ({group} options are {type(options).__name__}, "
            "not a mapping of option names)"
        )
    interface = PART_INTERFACES[group].__name__
    if path not in registered_targets(group):
        raise DataError(
            f"{source}: refused the {group} class {path!r}: it is not a registered "
            f"{interface} plugin (a model file may name only classes that an installed "
            "config group names as _target_; relocfw task=plugins lists them), so nothing "
            "was imported or run"
        )
    found = import_class(path, source)
    if not (isinstance(found, type) and issubclass(found, PART_INTERFACES[group])):
        raise DataError(
            f"{source}: refused the {group} class {path!r}: it is not a {interface} subclass"
        )
    return found


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

    The file holds the network, the map, the crop search, the query options, the
    calibrated error bounds where the pipeline has them, and the refiner where it can
    be stored (`PoseRefiner.saves_state`: refine=retrieval, features, features_rgb,
    sequence; a features refiner with its map's structure, so the loaded model needs
    no map image, depth file or cache). A refiner that cannot (a plugin without
    `state`) is left out: see `stores_refiner`; the loaded model then answers with the
    network's pose.

    Args:
        path: the model file to write.
        relocalizer: a fitted Relocalizer.
        options: constructor options of "backbone", "index", "crop" and "refine" (the
            refiner's; a stored refiner is rebuilt with them, so give them as built).
        metadata: plain values describing the data (dataset settings, sizes, names).

    Raises:
        ConfigError: a part's class is not a registered plugin (see load_model).
    """
    # The torch network, also when an inference engine runs it (engine=onnx).
    network = trained_network(relocalizer.backbone)
    parts = {
        "backbone": network,
        "index": relocalizer.index,
        "crop": relocalizer.search,
    }
    if stores_refiner(relocalizer):
        parts["refine"] = relocalizer.refiner
    payload: dict[str, Any] = {
        "kind": MODEL_KIND,
        "format": MODEL_FORMAT,
        "query": relocalizer.options.as_dict(),
        "metadata": metadata,
    }
    for name, part in parts.items():
        payload[name] = {
            "class": registered_class_path(part, name),
            "options": dict(options.get(name, {})),
        }
    payload["backbone"]["state"] = {k: v.detach().cpu() for k, v in network.state_dict().items()}
    payload["index"]["state"] = relocalizer.index.state()
    if "refine" in parts:
        payload["refine"]["state"] = relocalizer.refiner.state()
    if relocalizer.search.wants_map:  # e.g. crop=rule: the map's descriptors and poses
        payload["crop"]["state"] = relocalizer.search.state()
    if relocalizer.map_poses:
        payload["map_poses"] = torch.tensor(
            [[*p.position, *p.quaternion] for p in relocalizer.map_poses], dtype=torch.float64
        )
    if bounds_fit(relocalizer, "refine" in parts):  # calibrated (calibrate.share)
        payload["error_bounds"] = relocalizer.bounds.state()
    save_atomic(payload, Path(path))
    return Path(path)


def bounds_fit(relocalizer: Relocalizer, refiner_stored: bool) -> bool:
    """Whether the relocalizer's error bounds describe the answers a loaded file gives:
    bounds ranked by the refiner's confidence do not, where the refiner is left out
    (the loaded model answers with the network's pose and no confidence)."""
    bounds = relocalizer.bounds
    if bounds is None:
        return False
    return refiner_stored or bounds.signal != CONFIDENCE


def stores_refiner(relocalizer: Relocalizer) -> bool:
    """True when `save_model` stores the relocalizer's refiner; False without one, or
    for one without `state` / `load_state` (the caller may say it was left out)."""
    refiner = relocalizer.refiner
    return refiner is not None and bool(getattr(refiner, "saves_state", False))


def load_model(
    path: Path,
    device: str | torch.device = "cpu",
    overrides: Mapping[str, Any] | None = None,
) -> Relocalizer:
    """The Relocalizer saved in `path`, ready to localize.

    Args:
        path: a model file written by `save_model` (task=relocalize's model.relocfw).
        device: where the network runs.
        overrides: QueryOptions fields to change from the file's (None values keep
            the file's), e.g. {"batch_size": 64, "scoring": "shared"}.

    A model file is data, but loading one builds its parts: it trusts the installed
    plugins, not the file. Each part's class must be a `_target_` registered by a
    config group (relocfw's own or an installed plugin package's) and implement that
    part's interface; anything else is refused before it is imported.

    A damaged part (options that do not fit the weights, NaN weights or map, a map of
    other descriptors than the network makes) is refused here, in one line naming the
    file and the part, not left to fail at the first query.

    Raises:
        DataError: not a model file of this format, damaged, naming a class that is not
            a registered plugin of the right interface, or a torch too old to read it
            safely (relocfw.model.checkpoints.SAFE_TORCH).
        ConfigError: an override that is not a query option or not valid.
    """
    path = Path(path)
    payload = read_torch_file(path, "model")
    if not isinstance(payload, dict) or payload.get("kind") != MODEL_KIND:
        raise DataError(f"{path} is not a relocfw model file")
    if payload.get("format") not in READABLE_FORMATS:
        raise DataError(
            f"{path} is model format {payload.get('format')}; this relocfw reads formats "
            f"{', '.join(map(str, READABLE_FORMATS))}: run `relocfw task=relocalize` "
            "again with this version to write a new one"
        )
    stored = stored_options(payload, path)  # formats 2 and 3: retrieval_k -> "refine"
    # Every class is checked before any part is built: a refused crop class must not
    # leave a half-built backbone behind, nor follow work done for it.
    groups = [g for g in PART_INTERFACES if g in REQUIRED_PARTS or g in payload]
    classes = {group: plugin_class(payload, group, path) for group in groups}
    map_poses = stored_map_poses(payload, path)
    metadata = stored_metadata(payload, path)
    backbone = stored_backbone(payload, classes["backbone"], path)
    index = stored_index(payload, classes["index"], path)
    check_descriptor_dims(backbone, index, path)
    crop = stored_crop(payload, classes["crop"], path)
    refiner = stored_refiner(payload, classes, path)
    given = {k: v for k, v in dict(overrides or {}).items() if v is not None}

    def settled(values: dict[str, Any]) -> dict[str, Any]:
        # Re-ranking re-scores shared or scout candidates: with plain scoring (asked for now, or
        # a format 2 file, which did not store its scoring) a stored rerank is moot.
        if values.get("scoring", "plain") == "plain" and "rerank" not in given:
            values["rerank"] = 1
        return values

    try:
        QueryOptions.from_mapping(settled(dict(stored)), where=f"{path}: query options")
    except ConfigError as error:
        raise DataError(f"damaged model file: {error}") from error
    options = QueryOptions.from_mapping(settled({**stored, **given}), where="query")
    relocalizer = Relocalizer(backbone, index, crop, options, device, refiner)
    if map_poses is not None:
        relocalizer.map_poses = map_poses
    relocalizer.metadata = metadata
    bounds = stored_bounds(payload, path)
    if bounds is not None and bounds.signal == CONFIDENCE and refiner is None:
        raise DataError(
            f"{path}: damaged model file (error_bounds are ranked by a refiner's "
            "confidence, and the file has no refiner)"
        )
    # Options that change the answers also change their errors: bounds calibrated with
    # the file's options do not describe them (batch sizes only group the work).
    changed = [
        key
        for key, value in given.items()
        if key not in ANSWER_NEUTRAL_OPTIONS and stored.get(key) != value
    ]
    relocalizer.bounds = None if changed else bounds
    if changed and bounds is not None:
        relocalizer.metadata = {**metadata, "bounds_dropped_for": changed}
    return relocalizer


def stored_bounds(payload: dict[str, Any], path: Path) -> ErrorBounds | None:
    """The file's calibrated error bounds, checked (relocfw.core.error_bounds); None
    for a file without (written without calibrate.share, or before bounds existed)."""
    if "error_bounds" not in payload:
        return None
    state = payload["error_bounds"]
    if not isinstance(state, dict) or not all(isinstance(key, str) for key in state):
        raise DataError(f"{path}: damaged model file (error_bounds is not a mapping)")
    return ErrorBounds.from_state(state, f"{path}: error_bounds")
