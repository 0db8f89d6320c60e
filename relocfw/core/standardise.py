"""z-score standardisation and nearest-neighbour distances shared by the indexes."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch

from relocfw.core.errors import DataError

ROWS_AT_A_TIME = 16384  # chunk size for work over a whole map (10^6 rows is 8 GB)
# A dimension whose spread on the map is below this fraction of the median spread is a
# (nearly) dead ReLU unit: it has no spread of its own to standardise by. Dividing by
# its own std (1e-9) would turn a 1e-6 wobble into a z-score of 1000 that decides
# every distance alone, and dividing by a small floor would still make a unit that
# fires on a query crop but never on the map outweigh every live unit (a trained
# demo map has about 900 of 2048 units dead). Such dimensions are scaled like a
# typical one instead: by the median spread.
DEAD_FRACTION = 0.01
# A spread below this fraction of a dimension's mean is rounding in the mean itself
# (a constant 0.1 leaves a std near 1e-17), not variation.
ROUNDING = 1e-12


def row_chunks(count: int, rows: int = ROWS_AT_A_TIME) -> Iterator[slice]:
    """Slices of at most `rows` rows covering 0..count."""
    for start in range(0, count, rows):
        yield slice(start, min(start + rows, count))


def floored_scales(std: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Each dimension's std; the median spread for (nearly) dead dimensions.

    A dimension is dead when its std is below DEAD_FRACTION x the median std of the
    dimensions that vary. Where no dimension varies at all there is no typical spread,
    and every scale is 1.0 (descriptors are then only centred).
    """
    varies = std > ROUNDING * np.abs(mean)
    if not varies.any():
        return np.ones_like(std)
    typical = np.median(std[varies])
    return np.where(varies & (std >= DEAD_FRACTION * typical), std, typical)


class ZScore:
    """Per-dimension standardisation fitted on the map's descriptors.

    Each dimension is divided by its spread; a constant or nearly dead unit (spread
    below DEAD_FRACTION, 1%, of the median spread: dead ReLUs) is divided by the median
    spread instead, like a typical unit. It is then neither a division by zero nor,
    when a query crop moves it, a z-score in the millions or hundreds that outweighs
    every live dimension. Where no dimension varies, every scale is 1. Fitting goes
    chunk by chunk in float64 (mean, then spread about it), so a float32 map of any
    size is never copied whole.
    """

    def fit(self, features: np.ndarray, rows_at_a_time: int = ROWS_AT_A_TIME) -> ZScore:
        """Fit on [N, D] descriptors, `rows_at_a_time` rows per step."""
        features = checked_descriptors(features, rows_at_a_time=rows_at_a_time)
        count = len(features)
        chunks = list(row_chunks(count, rows_at_a_time))
        self.mean = sum(features[part].sum(axis=0, dtype=np.float64) for part in chunks) / count
        squares = sum(np.square(features[part] - self.mean).sum(axis=0) for part in chunks)
        self.std = floored_scales(np.sqrt(squares / count), self.mean)
        return self

    def state(self) -> dict[str, torch.Tensor]:
        return {"mean": torch.from_numpy(self.mean), "std": torch.from_numpy(self.std)}

    def load_state(self, state: dict[str, torch.Tensor]) -> ZScore:
        """What `state` returned. A saved state is data from anyone: a NaN mean or a
        zero spread would make every distance NaN, so it is refused here.

        Raises:
            DataError: mean or std missing, not vectors of one length, not finite, or
                a spread not above 0.
        """
        mean, std = state_vector(state, "mean"), state_vector(state, "std")
        if mean.shape != std.shape:
            raise DataError(f"standardisation: mean has {len(mean)} values but std {len(std)}")
        if not (np.isfinite(mean).all() and np.isfinite(std).all()):
            raise DataError("standardisation: mean or std holds NaN or infinite values")
        if not (std > 0).all():
            raise DataError("standardisation: every std must be above 0 (it divides)")
        self.mean, self.std = mean, std
        return self

    def __call__(self, features: np.ndarray) -> np.ndarray:
        return (np.asarray(features, dtype=np.float64) - self.mean) / self.std


def state_vector(state: dict[str, torch.Tensor], key: str) -> np.ndarray:
    """state[key] as a non-empty float64 vector, or a DataError naming `key`."""
    value = state.get(key) if isinstance(state, dict) else None
    if not isinstance(value, torch.Tensor) or value.ndim != 1 or len(value) == 0:
        raise DataError(f"standardisation: {key} must be a non-empty vector, got {shape_of(value)}")
    return value.double().numpy()


def shape_of(value: object) -> str:
    """A tensor's shape, or what else `value` is (for a one-line error)."""
    if isinstance(value, torch.Tensor):
        return f"shape {list(value.shape)}"
    return "nothing" if value is None else f"a {type(value).__name__}"


def finite_rows(state: dict[str, torch.Tensor], key: str, dim: int) -> np.ndarray:
    """state[key] as a float64 [N >= 1, dim] array of finite values, or a DataError
    naming `key` (an index's map, loaded from a file)."""
    value = state.get(key) if isinstance(state, dict) else None
    if not isinstance(value, torch.Tensor) or value.ndim != 2 or len(value) == 0:
        raise DataError(
            f"index state: {key} must be a non-empty [N, {dim}] array, got {shape_of(value)}"
        )
    if value.shape[1] != dim:
        raise DataError(
            f"index state: {key} has {value.shape[1]} dimensions, the standardisation {dim}"
        )
    rows = value.double().numpy()
    for part in row_chunks(len(rows)):  # a small boolean temporary, as for descriptors
        if not np.isfinite(rows[part]).all():
            raise DataError(f"index state: {key} holds NaN or infinite values")
    return rows


def checked_descriptors(
    features: np.ndarray, dim: int | None = None, rows_at_a_time: int = ROWS_AT_A_TIME
) -> np.ndarray:
    """[N, D] finite descriptors, float32 or float64 as given (no copy of a large map).

    Finiteness is checked `rows_at_a_time` rows at a time, so the check's boolean
    temporary stays small.

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
    for part in row_chunks(len(features), rows_at_a_time):
        if not np.isfinite(features[part]).all():
            raise DataError("descriptors contain NaN or infinity")
    return features


def check_features(features: np.ndarray, dim: int | None = None) -> np.ndarray:
    """[N, D] finite float64 descriptors, or a DataError saying what is wrong."""
    return checked_descriptors(np.asarray(features, dtype=np.float64), dim)


def k_nearest(
    queries: np.ndarray, points: np.ndarray, k: int, chunk: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """[n, k] Euclidean distances to, and indices of, the k nearest points, closest first.

    Uses |a|^2 + |b|^2 - 2ab (one matrix product) for `chunk` queries at a time, so
    memory stays bounded for large maps. By default a chunk's distance matrix holds
    about 2^24 entries (128 MB).
    """
    k = min(k, len(points))
    if chunk is None:
        chunk = max(1, 2**24 // max(1, len(points)))
    point_norms = np.einsum("ij,ij->i", points, points)
    distances = np.empty((len(queries), k))
    indices = np.empty((len(queries), k), dtype=np.int64)
    for part in row_chunks(len(queries), chunk):
        q = queries[part]
        squared = np.einsum("ij,ij->i", q, q)[:, None] + point_norms[None, :] - 2 * q @ points.T
        if k < len(points):
            best = np.argpartition(squared, k - 1, axis=1)[:, :k]
        else:
            best = np.broadcast_to(np.arange(len(points)), squared.shape)
        order = np.argsort(np.take_along_axis(squared, best, axis=1), axis=1, kind="stable")
        best = np.take_along_axis(best, order, axis=1)
        indices[part] = best
        distances[part] = np.sqrt(np.maximum(np.take_along_axis(squared, best, axis=1), 0))
    return distances, indices


def nearest(
    queries: np.ndarray, points: np.ndarray, chunk: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Distance to, and index of, the nearest point for each query (`chunk`: k_nearest's)."""
    distances, indices = k_nearest(queries, points, 1, chunk)
    return distances[:, 0], indices[:, 0]
