"""RootSIFT descriptors as a few bytes each: the uint8 grid, or product quantisation.

A map of 10^5 images holds about 10^8 descriptors, so what one costs decides whether
the map fits on a disk and in a page cache. Two codes:

- "grid": the 128 components as round(255 x value), 128 bytes, exactly the grid the
  builders put every map descriptor on (relocfw.structure.structure_map.quantised),
  so a grid-coded map matches as the map in memory does.
- "pq": product quantisation (Jegou, Douze and Schmid, PAMI 2011). The 128
  components are cut into S consecutive blocks of 128 / S; each block is replaced by
  the index (one byte) of its nearest of 256 centres, k-means centres of that block
  over the map's own descriptors. S bytes per descriptor (16: an eighth of the grid).
  Matching reads the decoded descriptor (each block's centre), so the query's own
  descriptor stays exact and only the map side carries the quantisation error (the
  asymmetric distance of the paper).

The centres are trained with faiss (relocfw[faiss]); encoding and decoding are plain
numpy, so a map is read without faiss and its codes do not depend on faiss's build.
"""

from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass

import numpy as np

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import integer_at_least
from relocfw.structure.features import SIFT_DIMENSIONS
from relocfw.structure.structure_map import dequantised, quantised

GRID = "grid"
PQ = "pq"
CENTRES = 256  # one byte per block
# Descriptors encoded per step: bounds the [rows, 256] distance temporaries.
ROWS_PER_STEP = 65536
# faiss's k-means samples 256 rows per centre anyway; drawing them here keeps the
# sample ours (seeded) rather than faiss's.
MOST_TRAINING_ROWS = CENTRES * 256


@dataclass(frozen=True, eq=False)
class DescriptorCodec:
    """How descriptors become bytes and back.

    Attributes:
        centres: None for the "grid" code; for "pq", [S, 256, 128 / S] float32, block
            s's 256 centres.

    Raises:
        DataError: when `centres` is not a finite float32 [S, 256, 128 / S] array with
            S dividing 128.
    """

    centres: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.centres is None:
            return
        centres = np.array(self.centres)
        blocks = centres.shape[0] if centres.ndim == 3 else 0
        if (
            centres.dtype != np.float32
            or blocks == 0
            or SIFT_DIMENSIONS % blocks
            or centres.shape != (blocks, CENTRES, SIFT_DIMENSIONS // blocks)
        ):
            raise DataError(
                f"product quantiser centres must be float32 [S, {CENTRES}, 128 / S] with S "
                f"dividing 128, got {centres.dtype} {list(centres.shape)}"
            )
        if not np.isfinite(centres).all():
            raise DataError("product quantiser centres hold NaN or infinite values")
        centres.setflags(write=False)
        object.__setattr__(self, "centres", centres)

    @property
    def kind(self) -> str:
        """GRID or PQ."""
        return GRID if self.centres is None else PQ

    @property
    def code_bytes(self) -> int:
        """Bytes per descriptor: 128 for the grid, S for a product quantiser."""
        return SIFT_DIMENSIONS if self.centres is None else int(self.centres.shape[0])

    def encode(self, descriptors: np.ndarray) -> np.ndarray:
        """[N, 128] RootSIFT descriptors to [N, code_bytes] uint8 codes.

        Raises:
            DataError: when `descriptors` is not [N, 128], or (grid) a value lies
                outside [0, 1].
        """
        values = np.asarray(descriptors, dtype=np.float32)
        if values.ndim != 2 or values.shape[1] != SIFT_DIMENSIONS:
            raise DataError(
                f"descriptors must be [N, {SIFT_DIMENSIONS}] (RootSIFT), got {list(values.shape)}"
            )
        if self.centres is None:
            return quantised(values)
        blocks, _, width = self.centres.shape
        codes = np.empty((len(values), blocks), dtype=np.uint8)
        squared_centres = np.einsum("sck,sck->sc", self.centres, self.centres)
        for start in range(0, len(values), ROWS_PER_STEP):
            part = values[start : start + ROWS_PER_STEP].reshape(-1, blocks, width)
            for block in range(blocks):
                # |x - c|^2 up to |x|^2, which is the same for every centre.
                scores = squared_centres[block] - 2.0 * part[:, block] @ self.centres[block].T
                codes[start : start + len(part), block] = np.argmin(scores, axis=1)
        return codes

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """[N, code_bytes] uint8 codes to [N, 128] float32 descriptors.

        Raises:
            DataError: when `codes` is not uint8 [N, code_bytes].
        """
        codes = np.asarray(codes)
        if codes.dtype != np.uint8 or codes.ndim != 2 or codes.shape[1] != self.code_bytes:
            raise DataError(
                f"descriptor codes must be uint8 [N, {self.code_bytes}], got {codes.dtype} "
                f"{list(codes.shape)}"
            )
        if self.centres is None:
            return dequantised(codes)
        blocks = self.centres.shape[0]
        # Row n, block s: centres[s, codes[n, s]]; blocks laid side by side.
        return self.centres[np.arange(blocks), codes].reshape(len(codes), SIFT_DIMENSIONS)


def grid_codec() -> DescriptorCodec:
    """The uint8 grid: 128 bytes, exact for maps the builders made."""
    return DescriptorCodec(None)


def codec_of_bytes(code_bytes: int, descriptors: np.ndarray, seed: int = 0) -> DescriptorCodec:
    """The grid for 128 bytes, else a product quantiser of `code_bytes` blocks trained
    on `descriptors` (`train_product_quantiser`)."""
    if code_bytes == SIFT_DIMENSIONS:
        return grid_codec()
    return train_product_quantiser(descriptors, code_bytes, seed)


def train_product_quantiser(
    descriptors: np.ndarray, code_bytes: int = 16, seed: int = 0
) -> DescriptorCodec:
    """A product quantiser of `code_bytes` blocks, trained on map descriptors.

    Args:
        descriptors: [N, 128] RootSIFT descriptors of the map (N >= 256; at most
            MOST_TRAINING_ROWS of them, drawn with `seed`, are used).
        code_bytes: blocks S, one byte each; a divisor of 128 below 128.
        seed: seeds the sample and faiss's k-means.

    Raises:
        ConfigError: when `code_bytes` does not divide 128, or faiss is missing.
        DataError: when there are fewer than 256 descriptors or they are not [N, 128].
    """
    code_bytes = integer_at_least("code_bytes", code_bytes, 1)
    if code_bytes >= SIFT_DIMENSIONS or SIFT_DIMENSIONS % code_bytes:
        raise ConfigError(
            f"code_bytes must divide {SIFT_DIMENSIONS} and be below it for a product "
            f"quantiser (e.g. 8, 16, 32, 64), got {code_bytes}"
        )
    values = np.asarray(descriptors, dtype=np.float32)
    if values.ndim != 2 or values.shape[1] != SIFT_DIMENSIONS:
        raise DataError(f"descriptors must be [N, {SIFT_DIMENSIONS}], got {list(values.shape)}")
    if len(values) < CENTRES:
        raise DataError(
            f"a product quantiser needs at least {CENTRES} training descriptors, got {len(values)}"
        )
    rng = np.random.default_rng(seed)
    if len(values) > MOST_TRAINING_ROWS:
        values = values[np.sort(rng.choice(len(values), MOST_TRAINING_ROWS, replace=False))]
    faiss = imported_faiss()
    quantiser = faiss.ProductQuantizer(SIFT_DIMENSIONS, code_bytes, 8)
    quantiser.cp.seed = seed
    # faiss warns (once per block) below 39 rows per centre; a small map's coarser
    # centres are its own business, and 16 identical warnings help no one.
    quantiser.cp.min_points_per_centroid = 1
    quantiser.verbose = False
    quantiser.train(np.ascontiguousarray(values))
    centres = faiss.vector_to_array(quantiser.centroids).astype(np.float32)
    return DescriptorCodec(centres.reshape(code_bytes, CENTRES, SIFT_DIMENSIONS // code_bytes))


def imported_faiss():
    """faiss, or a ConfigError saying how to install it."""
    # faiss's loader logs at INFO each CPU variant it tries; only its warnings matter.
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)
    try:
        return importlib.import_module("faiss")
    except ImportError as error:
        raise ConfigError(
            'product-quantised map descriptors need faiss-cpu: pip install "relocfw[faiss]"'
        ) from error
