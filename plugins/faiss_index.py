"""A map of 10^5 to 10^6 descriptors with faiss: exact (flat), IVF or HNSW search.

Descriptors are z-scored as in the other indexes, then optionally PCA-reduced and/or
stored as float16, and searched for the nearest one. kind=flat is exact: it returns
the same neighbours and (to float32 rounding) the same distances as index=exhaustive.
IVF and HNSW trade recall for speed; `benchmarks/index_scale.py` measures both.

Large maps never pass through float64: statistics are accumulated and vectors are
standardised and added chunk by chunk, so memory is the input plus the index itself.
Install with `pip install "relocfw[faiss]"` (faiss-cpu).
"""

from __future__ import annotations

import importlib
import logging

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.interfaces import SimilarityIndex
from relocfw.core.options import integer_at_least
from relocfw.core.standardise import ROWS_AT_A_TIME, ZScore, checked_descriptors, row_chunks

KINDS = ("flat", "ivf", "hnsw")
PRECISIONS = ("float32", "float16")


def import_faiss():
    # faiss's loader logs at INFO every CPU variant it tries and misses (AVX512, AVX2),
    # which under the CLI's logging reads like an error. Only its warnings matter here.
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)
    try:
        return importlib.import_module("faiss")
    except ImportError as error:
        raise ConfigError('index=faiss needs faiss-cpu: pip install "relocfw[faiss]"') from error


class FaissIndex(SimilarityIndex):
    """Nearest z-scored training descriptor, found by faiss.

    Args:
        kind: "flat" (exact), "ivf" (inverted lists over k-means cells) or "hnsw"
            (graph search).
        precision: "float32" or "float16" (half the memory per descriptor).
        pca_dim: reduce descriptors to this many dimensions first (0: keep all).
        nlist: IVF cells; the map needs at least this many descriptors.
        nprobe: IVF cells visited per query (more: higher recall, slower).
        hnsw_m: HNSW neighbours per node (memory and recall grow with it).
        ef_construction: HNSW candidate list while building.
        ef_search: HNSW candidate list while searching (more: higher recall, slower).
        seed: seeds the PCA and IVF training sample.
        rows_at_a_time: map rows standardised and added per step while fitting (bounds
            the float32 copy made of each step); the index is the same for any value.
    """

    def __init__(
        self,
        kind: str = "flat",
        precision: str = "float32",
        pca_dim: int = 0,
        nlist: int = 1024,
        nprobe: int = 16,
        hnsw_m: int = 32,
        ef_construction: int = 64,
        ef_search: int = 64,
        seed: int = 0,
        rows_at_a_time: int = ROWS_AT_A_TIME,
    ) -> None:
        if kind not in KINDS:
            raise ConfigError(f"index.kind must be one of {', '.join(KINDS)}, got {kind!r}")
        if precision not in PRECISIONS:
            raise ConfigError(
                f"index.precision must be one of {', '.join(PRECISIONS)}, got {precision!r}"
            )
        self.kind = kind
        self.precision = precision
        self.pca_dim = integer_at_least("pca_dim", pca_dim, 0)
        self.nlist = integer_at_least("nlist", nlist, 1)
        self.nprobe = integer_at_least("nprobe", nprobe, 1)
        self.hnsw_m = integer_at_least("hnsw_m", hnsw_m, 2)
        self.ef_construction = integer_at_least("ef_construction", ef_construction, 1)
        self.ef_search = integer_at_least("ef_search", ef_search, 1)
        self.seed = integer_at_least("seed", seed, 0)
        self.rows_at_a_time = integer_at_least("rows_at_a_time", rows_at_a_time, 1)
        self.faiss = import_faiss()

    def check_map_size(self, count: int) -> None:
        if self.kind == "ivf" and self.nlist > count:
            raise ConfigError(
                f"index.nlist={self.nlist} is more IVF cells than map descriptors ({count}); "
                f"choose nlist <= {count} (about sqrt(N) is usual)"
            )
        if self.pca_dim > count:
            raise ConfigError(
                f"index.pca_dim={self.pca_dim} needs at least that many map descriptors ({count})"
            )

    def _standardised(self, features: np.ndarray) -> np.ndarray:
        return self.zscore(features).astype(np.float32)

    def _empty_index(self, dim: int):
        faiss = self.faiss
        half = self.precision == "float16"
        if self.kind == "flat":
            if half:
                return faiss.IndexScalarQuantizer(dim, faiss.ScalarQuantizer.QT_fp16)
            return faiss.IndexFlatL2(dim)
        if self.kind == "ivf":
            quantizer = faiss.IndexFlatL2(dim)
            if half:
                index = faiss.IndexIVFScalarQuantizer(
                    quantizer, dim, self.nlist, faiss.ScalarQuantizer.QT_fp16
                )
            else:
                index = faiss.IndexIVFFlat(quantizer, dim, self.nlist)
            index.own_fields = True
            quantizer.this.disown()  # owned by the IVF index from here on
            return index
        if half:
            index = faiss.IndexHNSWSQ(dim, faiss.ScalarQuantizer.QT_fp16, self.hnsw_m)
        else:
            index = faiss.IndexHNSWFlat(dim, self.hnsw_m)
        index.hnsw.efConstruction = self.ef_construction
        return index

    def _training_sample(self, features: np.ndarray) -> np.ndarray:
        """Standardised rows for PCA / IVF training: at most 64 per cell, as faiss advises."""
        wanted = max(self.nlist * 64, self.pca_dim * 4, 1)
        if len(features) <= wanted:
            return self._standardised(features)
        rows = np.random.default_rng(self.seed).choice(len(features), wanted, replace=False)
        return self._standardised(features[np.sort(rows)])

    def fit(self, features: np.ndarray) -> None:
        features = checked_descriptors(features, rows_at_a_time=self.rows_at_a_time)
        self.check_map_size(len(features))
        self.zscore = ZScore().fit(features, self.rows_at_a_time)
        dim = features.shape[1]
        index = self._empty_index(self.pca_dim or dim)
        if self.pca_dim:
            pca = self.faiss.PCAMatrix(dim, self.pca_dim)
            index = self.faiss.IndexPreTransform(pca, index)
        if not index.is_trained:  # PCA, IVF: faiss seeds its k-means itself (fixed seed)
            index.train(self._training_sample(features))
        self._reserve(index, len(features))
        for part in row_chunks(len(features), self.rows_at_a_time):
            index.add(self._standardised(features[part]))
        self.index = index
        self.dim = dim
        self._configure_search()

    def _reserve(self, index, count: int) -> None:
        """Allocate flat storage for `count` vectors up front.

        Adding chunk by chunk otherwise grows faiss's std::vector by doubling, and while
        it moves, old and new buffers coexist: 1.5x the index at its peak, which at
        10^6 x 2048 floats ran a 24 GB machine out of memory. Resizing up, then to zero,
        keeps the capacity (std::vector never shrinks it on resize).
        """
        if isinstance(index, self.faiss.IndexPreTransform):
            index = self.faiss.downcast_index(index.index)
        storage = getattr(index, "storage", index)  # HNSW keeps vectors in a flat index
        storage = self.faiss.downcast_index(storage)
        if isinstance(storage, self.faiss.IndexFlatCodes):
            storage.codes.resize(count * storage.code_size)
            storage.codes.resize(0)

    def _configure_search(self) -> None:
        inner = self.index
        if isinstance(inner, self.faiss.IndexPreTransform):
            inner = self.faiss.downcast_index(inner.index)
        if self.kind == "ivf":
            self.faiss.extract_index_ivf(inner).nprobe = self.nprobe
        elif self.kind == "hnsw":
            inner.hnsw.efSearch = self.ef_search

    @property
    def bytes_per_descriptor(self) -> float:
        """Serialized index size over map size: what one more map image costs in memory.

        Counted as faiss writes it, without holding a serialized copy (8 GB at 10^6).
        """
        written = 0

        def count(chunk: bytes) -> int:
            nonlocal written
            written += len(chunk)
            return len(chunk)

        self.faiss.write_index(self.index, self.faiss.PyCallbackIOWriter(count))
        return written / self.index.ntotal

    def state(self) -> dict[str, torch.Tensor]:
        blob = self.faiss.serialize_index(self.index)  # a uint8 numpy array of its own
        return {
            **self.zscore.state(),
            "faiss_index": torch.from_numpy(blob),
        }

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """What `state` returned; a DataError naming the key for anything else. An
        index of another dimension than the standardisation would load and fail at
        the first query: it is refused here."""
        zscore = ZScore().load_state(state)
        blob = state.get("faiss_index")
        if not isinstance(blob, torch.Tensor) or blob.dtype != torch.uint8 or blob.ndim != 1:
            raise DataError("faiss state: faiss_index must be the index's bytes (uint8)")
        try:
            index = self.faiss.deserialize_index(blob.numpy())
        except RuntimeError as error:  # faiss says what it could not read
            first = str(error).strip().splitlines()[0] if str(error).strip() else "unreadable"
            raise DataError(f"faiss state: faiss_index cannot be read ({first})") from error
        if index.d != len(zscore.mean):
            raise DataError(
                f"faiss state: faiss_index holds {index.d}-dimensional descriptors, the "
                f"standardisation {len(zscore.mean)}"
            )
        if index.ntotal < 1:
            raise DataError("faiss state: faiss_index holds no map descriptors")
        self.zscore, self.index, self.dim = zscore, index, len(zscore.mean)
        self._configure_search()

    def _search(self, features: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        if not hasattr(self, "index"):
            raise DataError("the index is not fitted yet: call fit() first")
        features = checked_descriptors(features, self.dim)
        squared, indices = self.index.search(self._standardised(features), k)
        distances = np.sqrt(np.maximum(squared.astype(np.float64), 0.0))
        # IVF may find fewer than k in the cells it visits; faiss marks those -1.
        distances[indices < 0] = np.inf
        return distances, indices.astype(np.int64)

    def neighbours(self, features: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """[n, k] Euclidean distances to and indices of the nearest map descriptors."""
        distances, indices = self._search(features, k)
        if (indices < 0).any():
            raise DataError(
                f"index=faiss ({self.kind}) found fewer than {k} neighbours in the cells "
                f"it visited; raise index.nprobe (now {self.nprobe})"
            )
        return distances, indices

    def distance(self, features: np.ndarray) -> np.ndarray:
        return self._search(features, 1)[0][:, 0]
