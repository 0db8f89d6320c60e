"""z-score standardisation and nearest-neighbour distances shared by the indexes."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch

from relocfw.errors import DataError

ROWS_AT_A_TIME = 16384  # chunk size for work over a whole map (10^6 rows is 8 GB)


def row_chunks(count: int) -> Iterator[slice]:
    """Slices of at most ROWS_AT_A_TIME rows covering 0..count."""
    for start in range(0, count, ROWS_AT_A_TIME):
        yield slice(start, min(start + ROWS_AT_A_TIME, count))


class ZScore:
    """Per-dimension standardisation fitted on the map's descriptors.

    Dimensions that never vary (dead ReLU units) keep a unit scale instead of
    dividing by zero. Fitting goes chunk by chunk in float64 (mean, then spread about
    it), so a float32 map of any size is never copied whole.
    """

    def fit(self, features: np.ndarray) -> ZScore:
        features = checked_descriptors(features)
        count = len(features)
        self.mean = sum(features[part].sum(axis=0, dtype=np.float64) for part in row_chunks(count))
        self.mean = self.mean / count
        squares = sum(
            np.square(features[part] - self.mean).sum(axis=0) for part in row_chunks(count)
        )
        std = np.sqrt(squares / count)
        self.std = np.where(std > 1e-12, std, 1.0)
        return self

    def state(self) -> dict[str, torch.Tensor]:
        return {"mean": torch.from_numpy(self.mean), "std": torch.from_numpy(self.std)}

    def load_state(self, state: dict[str, torch.Tensor]) -> ZScore:
        self.mean = state["mean"].double().numpy()
        self.std = state["std"].double().numpy()
        return self

    def __call__(self, features: np.ndarray) -> np.ndarray:
        return (np.asarray(features, dtype=np.float64) - self.mean) / self.std


def checked_descriptors(features: np.ndarray, dim: int | None = None) -> np.ndarray:
    """[N, D] finite descriptors, float32 or float64 as given (no copy of a large map).

    Raises:
        DataError: saying what is wrong (shape, dimensions, NaN or infinity).
    """
    features = np.asarray(features)
    if features.dtype not in (np.float32, np.float64):
        features = features.astype(np.float64)
    if features.ndim != 2 or len(features) == 0:
        raise DataError(f"expected a non-empty [N, D] descriptor array, got shape {features.shape}")
    if dim is not None and features.shape[1] != dim:
        raise DataError(f"descriptors have {features.shape[1]} dimensions, the map has {dim}")
    for part in row_chunks(len(features)):
        if not np.isfinite(features[part]).all():
            raise DataError("descriptors contain NaN or infinity")
    return features


def check_features(features: np.ndarray, dim: int | None = None) -> np.ndarray:
    """[N, D] finite float64 descriptors, or a DataError saying what is wrong."""
    return checked_descriptors(np.asarray(features, dtype=np.float64), dim)


def k_nearest(queries: np.ndarray, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """[n, k] Euclidean distances to, and indices of, the k nearest points, closest first.

    Uses |a|^2 + |b|^2 - 2ab (one matrix product) in chunks, so memory stays
    bounded for large maps.
    """
    k = min(k, len(points))
    point_norms = np.einsum("ij,ij->i", points, points)
    distances = np.empty((len(queries), k))
    indices = np.empty((len(queries), k), dtype=np.int64)
    chunk = max(1, 2**24 // max(1, len(points)))
    for start in range(0, len(queries), chunk):
        q = queries[start : start + chunk]
        squared = np.einsum("ij,ij->i", q, q)[:, None] + point_norms[None, :] - 2 * q @ points.T
        if k < len(points):
            best = np.argpartition(squared, k - 1, axis=1)[:, :k]
        else:
            best = np.broadcast_to(np.arange(len(points)), squared.shape)
        order = np.argsort(np.take_along_axis(squared, best, axis=1), axis=1, kind="stable")
        best = np.take_along_axis(best, order, axis=1)
        indices[start : start + chunk] = best
        distances[start : start + chunk] = np.sqrt(
            np.maximum(np.take_along_axis(squared, best, axis=1), 0)
        )
    return distances, indices


def nearest(queries: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance to, and index of, the nearest point for each query."""
    distances, indices = k_nearest(queries, points, 1)
    return distances[:, 0], indices[:, 0]
