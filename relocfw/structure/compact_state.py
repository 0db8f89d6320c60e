"""A CompactMap as a few tensors, and back: what a model file stores of refine=features
with map_store=compact.

A model file is one self-contained file read by torch's weights-only loader, so the
compact map travels as its own arrays (relocfw.structure.compact_map's layout), each
under its own key, rather than as the folder it was opened from:

- `compact_offsets` [M + 1] int64, `compact_codes` [T, B] uint8, `compact_points`
  [T, 3] float16 or float32 (camera-frame points), `compact_poses` [M, 7] float64,
  `compact_cameras` [M, 6] float64, `compact_names` [M, L] uint8 (each name's UTF-8
  bytes, zero-padded to the longest), and for a product quantiser `compact_centres`.
- map.json's meta as int64 scalars: `compact_format`, `compact_source` (index into
  SOURCES), `compact_codes_kind` (index into CODE_KINDS), `compact_code_bytes`,
  `compact_point_dtype` (index into POINT_DTYPES), `compact_images`, `compact_rows`.
  Indices, not strings: a tensor file holds no text, and an index is checked
  against a closed list.

The keys differ from relocfw.structure.map_state's (offsets, points, ...), so a state
holds one map or the other and is never misread as the other. `compact_of_state`
checks every tensor before the map is made (a model file is data from anyone) and
then makes it with CompactMap.of_arrays, which repeats every check CompactMap.open
makes; a fault is one DataError naming the tensor.
"""

from __future__ import annotations

import numpy as np
import torch

from relocfw.core.errors import DataError
from relocfw.structure.compact_map import COMPACT_FORMAT, COMPACT_KIND, POINT_DTYPES, CompactMap
from relocfw.structure.descriptor_codes import GRID, PQ
from relocfw.structure.map_state import checked_tensor
from relocfw.structure.structure_map import SOURCES

PREFIX = "compact_"
# Stored as indices: append, never reorder.
CODE_KINDS = (GRID, PQ)
# The array tensors and their dtypes (points: by compact_point_dtype).
ARRAY_DTYPES = {
    "offsets": torch.int64,
    "codes": torch.uint8,
    "poses": torch.float64,
    "cameras": torch.float64,
    "names": torch.uint8,
}
# The meta scalars (int64 each).
META_KEYS = ("format", "source", "codes_kind", "code_bytes", "point_dtype", "images", "rows")
TORCH_POINT_DTYPES = {"float16": torch.float16, "float32": torch.float32}


def holds_compact_map(state: dict[str, torch.Tensor]) -> bool:
    """Whether a state holds a compact map (any compact_ key)."""
    return any(str(key).startswith(PREFIX) for key in state)


def compact_state(compact: CompactMap) -> dict[str, torch.Tensor]:
    """The map's arrays and meta as tensors (copies: a memory-mapped map is read whole,
    as a model file must hold it)."""
    names = np.asarray(compact.names)
    width = max(1, names.dtype.itemsize)
    name_bytes = np.zeros((len(names), width), dtype=np.uint8)
    for row, name in enumerate(names.tolist()):
        name_bytes[row, : len(name)] = np.frombuffer(name, dtype=np.uint8)
    meta = {
        "format": COMPACT_FORMAT,
        "source": SOURCES.index(compact.source),
        "codes_kind": CODE_KINDS.index(compact.codec.kind),
        "code_bytes": compact.codec.code_bytes,
        "point_dtype": POINT_DTYPES.index(compact.points.dtype.name),
        "images": len(compact),
        "rows": len(compact.codes),
    }
    state = {
        f"{PREFIX}offsets": torch.from_numpy(np.array(compact.offsets, dtype=np.int64)),
        f"{PREFIX}codes": torch.from_numpy(np.array(compact.codes, dtype=np.uint8)),
        f"{PREFIX}points": torch.from_numpy(np.array(compact.points)),
        f"{PREFIX}poses": torch.from_numpy(np.array(compact.poses, dtype=np.float64)),
        f"{PREFIX}cameras": torch.from_numpy(np.array(compact.cameras, dtype=np.float64)),
        f"{PREFIX}names": torch.from_numpy(name_bytes),
        **{f"{PREFIX}{key}": torch.tensor(int(value)) for key, value in meta.items()},
    }
    if compact.codec.centres is not None:
        state[f"{PREFIX}centres"] = torch.from_numpy(np.array(compact.codec.centres))
    return state


def compact_of_state(state: dict[str, torch.Tensor], label: str) -> CompactMap:
    """The CompactMap `compact_state` stored, every tensor checked first.

    Raises:
        DataError: naming the tensor (compact_<name>) that is missing, of another
            dtype or shape, or holds values a map cannot.
    """
    meta_values = {}
    for key in META_KEYS:
        value = checked_tensor(state, PREFIX + key, torch.int64, label)
        if value.shape != ():
            raise DataError(f"{label}: {PREFIX}{key} must be one number, got {list(value.shape)}")
        meta_values[key] = int(value)
    if meta_values["format"] != COMPACT_FORMAT:
        raise DataError(
            f"{label}: {PREFIX}format is {meta_values['format']}; this relocfw reads "
            f"format {COMPACT_FORMAT}"
        )
    for key in ("code_bytes", "images", "rows"):
        if meta_values[key] < 0:
            raise DataError(f"{label}: {PREFIX}{key} must be at least 0, got {meta_values[key]}")
    if meta_values["images"] == 0:
        # A map without an image answers nothing; refused here, as fit refuses it.
        raise DataError(f"{label}: {PREFIX}images is 0: the map holds no image")
    meta = {
        "kind": COMPACT_KIND,
        "format": meta_values["format"],
        "source": indexed(SOURCES, meta_values["source"], "source", label),
        "codes": indexed(CODE_KINDS, meta_values["codes_kind"], "codes_kind", label),
        "code_bytes": meta_values["code_bytes"],
        "point_dtype": indexed(POINT_DTYPES, meta_values["point_dtype"], "point_dtype", label),
        "images": meta_values["images"],
        "rows": meta_values["rows"],
    }
    arrays = {
        name: checked_tensor(state, PREFIX + name, dtype, label)
        for name, dtype in ARRAY_DTYPES.items()
    }
    arrays["points"] = checked_tensor(
        state, f"{PREFIX}points", TORCH_POINT_DTYPES[meta["point_dtype"]], label
    )
    arrays["names"] = names_of_bytes(arrays["names"], label)
    centres = None
    if meta["codes"] == PQ:
        centres = checked_tensor(state, f"{PREFIX}centres", torch.float32, label)
    elif f"{PREFIX}centres" in state:
        raise DataError(f"{label}: {PREFIX}centres belong to product-quantised codes only")
    return CompactMap.of_arrays(arrays, meta, centres, label, PREFIX)


def indexed(choices: tuple[str, ...], code: int, key: str, label: str) -> str:
    """choices[code], or a DataError naming compact_<key> and the choices."""
    if not 0 <= code < len(choices):
        known = ", ".join(f"{number} ({name})" for number, name in enumerate(choices))
        raise DataError(f"{label}: {PREFIX}{key} must be one of {known}, got {code}")
    return choices[code]


def names_of_bytes(name_bytes: np.ndarray, label: str) -> np.ndarray:
    """[M] bytes names of a zero-padded [M, L] uint8 array, each valid UTF-8."""
    if name_bytes.ndim != 2 or name_bytes.shape[1] < 1:
        raise DataError(
            f"{label}: {PREFIX}names must be [M, L] UTF-8 bytes, got {list(name_bytes.shape)}"
        )
    width = name_bytes.shape[1]
    names = np.ascontiguousarray(name_bytes).view(f"S{width}").reshape(len(name_bytes))
    for number, name in enumerate(names.tolist()):
        try:
            name.decode("utf-8")
        except UnicodeDecodeError:
            raise DataError(f"{label}: {PREFIX}names[{number}] is not UTF-8") from None
    return names
