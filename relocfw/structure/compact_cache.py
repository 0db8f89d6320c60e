"""refine.map_store=compact: the cached structure map, written once as a compact map
folder beside its cache entry and answered from there, memory-mapped.

The structure cache holds a map as one npz file (relocfw.structure.structure_cache:
`cache_dir/structure/<key>.npz`), which is read whole into memory. A compact map
(relocfw.structure.compact_map) is a folder of flat arrays that is opened
memory-mapped, so a query reads only its keyframes' rows. The folder goes beside the
npz, named by the same content key (`<key>.compact/`), so one key names both and a
changed map (other images, poses, settings or code versions) gets another folder.

The writer (relocfw.structure.compact_writer) publishes all or nothing: the arrays
go to a hidden staging folder beside the target, map.json last, and when complete the
key's name (a link) is swapped to it in one rename; runs writing the same key at once
both succeed, and a run reading it meanwhile opens one whole map. So a folder under
the key's name either opens cleanly, and is reused, or is damaged by something else
and is rewritten. A folder
that opens but does not hold the map it is named after (copied over, or left by
code that wrote other rows) is rewritten too: its image names and per-image row
counts are compared with the StructureMap, which costs nothing beside building
that map, and every file's bytes with the SHA-256 map.json records of them
(compact_map.content_faults: an array rewritten at the same size is noticed; it reads
the whole folder once, 32 ms for 400 images of 607 points, about 0.1 s per 100 MB).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from relocfw.core.errors import DataError
from relocfw.structure.compact_map import CompactMap, content_faults
from relocfw.structure.compact_writer import save_compact_map
from relocfw.structure.descriptor_codes import grid_codec
from relocfw.structure.structure_map import StructureMap

# The code and point precision refine=features writes its maps with: the exact uint8
# grid (the map's own descriptors, bit for bit) and float16 camera-frame points
# (1.5 mm at 3 m; relocfw.structure.compact_map).
POINT_DTYPE = "float16"


def compact_folder(cache_dir: str | Path, key: str) -> Path:
    """`cache_dir/structure/<key>.compact`: beside the key's npz."""
    return Path(cache_dir).expanduser() / "structure" / f"{key}.compact"


def cached_compact_map(
    cache_dir: str | Path, key: str, structure: StructureMap, quiet: bool = False
) -> CompactMap:
    """The compact map of `structure` in `compact_folder(cache_dir, key)`, opened
    memory-mapped; written first (uint8 grid, float16 points) unless a folder there
    opens cleanly and holds `structure`'s images and rows.

    Raises:
        DataError: naming the image whose points do not fit float16 (a scene tens of
            kilometres deep), or the folder when it cannot be opened just after it
            was written.
    """
    folder = compact_folder(cache_dir, key)
    if folder.exists():
        try:
            compact = CompactMap.open(folder)
            faults = content_faults(compact)
            if not faults and holds(compact, structure):
                if not quiet:
                    print(f"map structure: reused compact {folder}", file=sys.stderr)
                return compact
            reason = faults[0] if faults else "holds another map"
        except DataError as error:
            reason = str(error)
        # Printed even when quiet, as cached_structure_map does: a cache entry that is
        # not what its name says is worth one line.
        print(f"note: compact map {folder} ({reason}): rewriting it", file=sys.stderr)
    save_compact_map(structure, folder, grid_codec(), POINT_DTYPE)
    if not quiet:
        print(f"map structure: wrote compact {folder}", file=sys.stderr)
    return CompactMap.open(folder)


def holds(compact: CompactMap, structure: StructureMap) -> bool:
    """Whether `compact` has `structure`'s images (by name, in order), source and each
    image's rows with a 3-D point (what save_compact_map keeps), in the grid code and
    point precision written here."""
    if len(compact) != len(structure) or compact.source != structure.source:
        return False
    if compact.codec.kind != grid_codec().kind or compact.points.dtype != np.dtype(POINT_DTYPE):
        return False
    counts = [int(np.isfinite(points).all(axis=1).sum()) for points in structure.points]
    if not np.array_equal(np.diff(compact.offsets), counts):
        return False
    names = [str(name).encode("utf-8") for name in structure.names]
    return np.asarray(compact.names).tolist() == names
