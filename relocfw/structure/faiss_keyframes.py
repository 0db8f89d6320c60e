"""refine.keyframe_search=faiss: the k map images nearest a query's descriptor, by faiss.

refine=features retrieves keyframes by the query crop's descriptor over the z-scored
map descriptors (relocfw.structure.refiner_inputs.keyframes_by_descriptor, an exact
numpy search). At 10^5 map images that search took 158 ms per query and faiss's
exact flat search over float16 storage 16.3 ms, with the same keyframes
(benchmarks/structure_scale.py, docs/results/structure.md). So this is the same
exact L2 search, in faiss: a flat index (every map image compared, no training, no
recall traded) over the descriptors stored as float16, which halves the bytes each
query scans; the float16 rounding (a relative 2^-11) could only swap two map images
whose distances are that close.

faiss is optional (relocfw[faiss]) and imported when this search is made, never at
import time, so the rest of the refiner works without it.
"""

from __future__ import annotations

import importlib
import logging

import numpy as np

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.standardise import ZScore, check_features

FAISS_HINT = 'refine.keyframe_search=faiss needs faiss-cpu: pip install -e ".[faiss]"'


def imported_faiss():
    """faiss, or a ConfigError naming refine.keyframe_search and how to install it."""
    # faiss's loader logs at INFO each CPU variant it tries and misses; only its
    # warnings matter (as plugins/faiss_index.import_faiss does).
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)
    try:
        return importlib.import_module("faiss")
    except ImportError as error:
        raise ConfigError(FAISS_HINT) from error


class FaissKeyframeSearch:
    """Exact nearest map images by descriptor, in a faiss flat index of float16 rows.

    Args:
        points: [M, D] z-scored map descriptors (the refiner's keyframe descriptors).

    Raises:
        ConfigError: when faiss is not installed (FAISS_HINT).
        DataError: when `points` is not [M, D] finite with M >= 1.
    """

    def __init__(self, points: np.ndarray) -> None:
        faiss = imported_faiss()
        rows = check_features(points)
        if len(rows) == 0:
            raise DataError("keyframe search needs at least one map descriptor")
        self.dimensions = rows.shape[1]
        self.index = faiss.IndexScalarQuantizer(self.dimensions, faiss.ScalarQuantizer.QT_fp16)
        self.index.add(np.ascontiguousarray(rows, dtype=np.float32))

    def __len__(self) -> int:
        return int(self.index.ntotal)

    def nearest(self, zscore: ZScore, descriptor: np.ndarray, count: int) -> list[int]:
        """The `count` map images nearest the query crop's `descriptor` (standardised
        with `zscore`, as the map's were), nearest first; at most the map's size."""
        wanted = check_features(np.asarray(descriptor)[None], self.dimensions)
        count = min(int(count), len(self))
        _, indices = self.index.search(np.ascontiguousarray(zscore(wanted), np.float32), count)
        return [int(i) for i in indices[0]]
