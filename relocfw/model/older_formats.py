"""What model files of earlier formats stored, read as today's (relocfw.model.model_file).

Format 2 kept four query options at the top level; formats 2 and 3 kept the
image-retrieval baseline as the query option `retrieval_k`, which is the refiner
refine=retrieval since format 4. Such a file is read as format 4 would have written it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import integer_at_least

# What format 2 stored of the query options, each at the top level.
FORMAT_2_QUERY_KEYS = ("retrieval_k", "crop_samples", "sample_seed", "rerank")
# Formats whose query options may hold retrieval_k.
RETRIEVAL_K_FORMATS = (2, 3)
# The refiner that answers for a format 2 or 3 file's retrieval_k > 0 (conf/refine/
# retrieval.yaml's _target_): its state is index=exhaustive's plus the map poses, both
# of which such a file holds when its index is the exhaustive one. The name still goes
# through the registry check of every part a file names.
RETRIEVAL_REFINER = "relocfw.plugins.retrieval_refiner.RetrievalRefiner"
# retrieval_k needed an index with `neighbours`: index=exhaustive, or index=faiss (or a
# third party's). Only the exhaustive index's state is the refiner's (z-scored float64
# descriptors); another index's state means something else and is refused, not guessed.
EXHAUSTIVE_INDEX = "relocfw.plugins.exhaustive_index.ExhaustiveIndex"


def stored_options(payload: dict[str, Any], path: Path) -> dict[str, Any]:
    """The query options a model file stores, as a mapping (format 2: its four keys).

    A format 2 or 3 file's retrieval_k is taken out of the mapping and, when above 0,
    put into `payload` as the "refine" part format 4 writes (`retrieval_part`).
    """
    if payload.get("format") == 2:
        query = {key: payload[key] for key in FORMAT_2_QUERY_KEYS if key in payload}
    else:
        query = payload.get("query")
        if not isinstance(query, dict):
            raise DataError(f"{path}: damaged model file (query options are not a mapping)")
        query = dict(query)
    if payload.get("format") in RETRIEVAL_K_FORMATS and "retrieval_k" in query:
        retrieval_part(payload, query.pop("retrieval_k"), path)
    return query


def retrieval_part(payload: dict[str, Any], retrieval_k: Any, path: Path) -> None:
    """Add to `payload` the "refine" part of refine=retrieval refine.k=`retrieval_k`
    (nothing for 0): its state the index's (index=exhaustive's z-scored map
    descriptors) and the map poses."""
    try:
        k = integer_at_least(f"{path}: query option retrieval_k", retrieval_k, 0)
    except ConfigError as error:
        raise DataError(f"damaged model file: {error}") from error
    if k == 0 or "refine" in payload:
        return
    index, poses = payload.get("index"), payload.get("map_poses")
    if not isinstance(index, dict) or not isinstance(index.get("state"), dict):
        raise DataError(f"{path}: damaged model file (index is not a mapping with a state)")
    if not isinstance(poses, torch.Tensor):
        raise DataError(f"{path}: damaged model file (retrieval_k={k} but no map poses)")
    if index.get("class") != EXHAUSTIVE_INDEX:
        raise DataError(
            f"{path}: an older model file with query option retrieval_k={k} and index "
            f"{index.get('class')!r}; this relocfw reads its retrieval only with "
            f"index=exhaustive: run `relocfw task=relocalize` again with refine=retrieval "
            f"refine.k={k} to write a new one"
        )
    payload["refine"] = {
        "class": RETRIEVAL_REFINER,
        "options": {"k": k},
        "state": {**index["state"], "poses": poses},
    }
