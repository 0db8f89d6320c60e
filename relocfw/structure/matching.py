"""Matching local descriptors: mutual nearest neighbours with Lowe's ratio test.

All distances of a query image's descriptors to a set of candidates come from ONE
matrix product (||q||^2 + ||c||^2 - 2 q c^T), the way BLAS does the most work per
byte; nothing loops over descriptors in Python. A match (i, j) is kept when

- j is query descriptor i's nearest candidate,
- i is candidate j's nearest query descriptor (mutual: a one-sided match is often a
  descriptor that is merely close to everything), and
- Lowe's ratio test passes: nearest distance < ratio x second-nearest distance
  (Lowe, IJCV 2004: a distinctive match is much closer than the next best one).

Matched against several views, one query keypoint may match in each of them; those
are several observations of ONE piece of the query's evidence. `one_match_per_query`
keeps each query keypoint's best match (the smallest descriptor distance; a tie goes
to the earlier view, i.e. the better-retrieved keyframe), so what a solver counts as
inliers counts distinct query keypoints, not rows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.structure.features import LocalFeatures


def checked_ratio(ratio: float) -> float:
    """`ratio` as a float in (0, 1], or a ConfigError naming it.

    Above 1 the second-nearest could be nearer than the nearest, which is no test;
    0 would refuse everything.
    """
    try:
        value = float(ratio)
    except (TypeError, ValueError):
        raise ConfigError(f"ratio must be a number in (0, 1], got {ratio!r}") from None
    if not (math.isfinite(value) and 0.0 < value <= 1.0):
        raise ConfigError(f"ratio must be in (0, 1] (Lowe's test; 0.8 is usual), got {ratio!r}")
    return value


def descriptor_tensor(descriptors: np.ndarray | torch.Tensor, name: str) -> torch.Tensor:
    """[N, D] descriptors as a CPU float tensor (float64 stays float64, other types
    become float32), or a DataError naming the argument."""
    try:
        if not isinstance(descriptors, torch.Tensor):
            array = np.asarray(descriptors)
            # torch warns on (and may not write to) a read-only array, such as the
            # descriptors of a frozen LocalFeatures: copy those, share the rest.
            descriptors = array if array.flags.writeable else array.copy()
        tensor = torch.as_tensor(descriptors)
    except (TypeError, ValueError, RuntimeError) as error:
        raise DataError(f"{name} must be an [N, D] array of numbers ({error})") from None
    if tensor.ndim != 2:
        raise DataError(
            f"{name} must be an [N, D] array of descriptors, got shape {tuple(tensor.shape)}"
        )
    if tensor.dtype != torch.float64:
        tensor = tensor.to(torch.float32)
    if not bool(torch.isfinite(tensor).all()):
        raise DataError(f"{name} holds NaN or infinite values")
    return tensor.cpu()


def squared_distances(query: torch.Tensor, candidates: torch.Tensor) -> torch.Tensor:
    """All squared Euclidean distances in one matrix product.

    Args:
        query: [N, D].
        candidates: [M, D], same dtype.

    Returns:
        [N, M] squared distances, clamped at 0 (the expansion can round a tiny
        distance below zero).
    """
    query_norms = (query * query).sum(dim=1, keepdim=True)  # [N, 1]
    candidate_norms = (candidates * candidates).sum(dim=1)[None, :]  # [1, M]
    # addmm fuses the product and the sum: norms - 2 q c^T in one BLAS call.
    return torch.addmm(query_norms + candidate_norms, query, candidates.T, alpha=-2.0).clamp_(
        min=0.0
    )


def matches_of_distances(distances: torch.Tensor, ratio: float) -> np.ndarray:
    """Mutual nearest neighbours passing the ratio test, from squared distances.

    Args:
        distances: [N, M] squared distances of N query descriptors to M candidates.
        ratio: Lowe's ratio, in (0, 1].

    Returns:
        [K, 2] int64 (query index, candidate index) pairs, in query order. Empty when
        N == 0 or M < 2 (with one candidate there is no second-nearest to test
        against, so no match can be shown to be distinctive).
    """
    count, candidates = distances.shape
    if count == 0 or candidates < 2:
        return np.zeros((0, 2), dtype=np.int64)
    two_nearest, two_indices = torch.topk(distances, k=2, dim=1, largest=False)  # [N, 2]
    nearest = two_indices[:, 0]
    # For each candidate, its nearest query descriptor (the first one on a tie).
    back = torch.argmin(distances, dim=0)  # [M]
    rows = torch.arange(count)
    mutual = back[nearest] == rows
    # d1 / d2 < ratio  <=>  d1^2 < ratio^2 d2^2 for distances >= 0; squared distances
    # need no square root, and a tie (d1 == d2, also 0 == 0) fails as it should.
    distinctive = two_nearest[:, 0] < (ratio * ratio) * two_nearest[:, 1]
    keep = mutual & distinctive
    return torch.stack([rows[keep], nearest[keep]], dim=1).to(torch.int64).numpy()


def mutual_nearest_neighbours(
    query: np.ndarray | torch.Tensor, candidates: np.ndarray | torch.Tensor, ratio: float = 0.8
) -> np.ndarray:
    """Mutual nearest neighbours of two descriptor sets that pass Lowe's ratio test.

    Args:
        query: [N, D] descriptors (e.g. LocalFeatures.descriptors).
        candidates: [M, D] descriptors, same D.
        ratio: Lowe's ratio in (0, 1]: keep a match when nearest / second-nearest
            distance < ratio (computed over the query descriptor's candidates).

    Returns:
        [K, 2] int64 pairs (query index, candidate index), in query order; [0, 2]
        when N == 0 or M < 2.

    Raises:
        DataError: naming `query` or `candidates` when it is not 2-D or holds NaN, or
            when their descriptor lengths differ.
        ConfigError: when `ratio` is not in (0, 1].
    """
    ratio = checked_ratio(ratio)
    query_t = descriptor_tensor(query, "query")
    candidates_t = descriptor_tensor(candidates, "candidates")
    if query_t.shape[1] != candidates_t.shape[1]:
        raise DataError(
            f"query descriptors have {query_t.shape[1]} dimensions, candidates "
            f"{candidates_t.shape[1]}; they must be the same kind of descriptor"
        )
    dtype = torch.promote_types(query_t.dtype, candidates_t.dtype)
    with torch.inference_mode():
        distances = squared_distances(query_t.to(dtype), candidates_t.to(dtype))
        return matches_of_distances(distances, ratio)


def match_against_views(
    query: LocalFeatures, views: Sequence[LocalFeatures], ratio: float = 0.8
) -> list[tuple[int, np.ndarray]]:
    """Match one query image's features against several views at once.

    All views' descriptors are stacked so the distances come from one matrix product;
    the mutual check and the ratio test then run per view on that view's columns, so
    each view's matches are exactly `mutual_nearest_neighbours(query, view)`: the
    second-nearest of the ratio test is the second-nearest within the same view (a
    similar descriptor in another view is a different observation, not an ambiguity).

    Args:
        query: the query image's LocalFeatures, N descriptors.
        views: the views' LocalFeatures (e.g. retrieved map images), same D.
        ratio: Lowe's ratio in (0, 1].

    Returns:
        One (view index, [K, 2] int64 pairs (query index, view keypoint index)) per
        view, in the order of `views`; a view without matches has a [0, 2] array.

    Raises:
        DataError: when a view's descriptors have another length than the query's
            (naming the view), or an entry of `views` is not LocalFeatures.
        ConfigError: when `ratio` is not in (0, 1].
    """
    ratio = checked_ratio(ratio)
    if not isinstance(query, LocalFeatures):
        raise DataError(f"query must be LocalFeatures, got {type(query).__name__}")
    dimensions = query.descriptors.shape[1]
    for number, view in enumerate(views):
        if not isinstance(view, LocalFeatures):
            raise DataError(f"views[{number}] must be LocalFeatures, got {type(view).__name__}")
        if view.descriptors.shape[1] != dimensions:
            raise DataError(
                f"views[{number}] has {view.descriptors.shape[1]}-dimensional descriptors, "
                f"the query {dimensions}-dimensional"
            )
    if not views:
        return []
    # LocalFeatures holds float32, finite, 2-D descriptors: no further checks needed.
    stacked = torch.from_numpy(np.concatenate([v.descriptors for v in views]))
    ends = np.cumsum([len(v) for v in views])
    starts = ends - np.array([len(v) for v in views])
    with torch.inference_mode():
        distances = squared_distances(torch.from_numpy(query.descriptors.copy()), stacked)
        return [
            (number, matches_of_distances(distances[:, start:end], ratio))
            for number, (start, end) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True))
        ]


def match_distances(query: LocalFeatures, view: LocalFeatures, pairs: np.ndarray) -> np.ndarray:
    """[K] float32 squared descriptor distances of (query index, view index) pairs."""
    if len(pairs) == 0:
        return np.zeros(0, dtype=np.float32)
    difference = query.descriptors[pairs[:, 0]] - view.descriptors[pairs[:, 1]]
    return np.einsum("ij,ij->i", difference, difference)


def one_match_per_query(query_indices: np.ndarray, distances: np.ndarray) -> np.ndarray:
    """The rows to keep so each query keypoint contributes once: its best match.

    Args:
        query_indices: [K] the query keypoint of each candidate row, the rows of the
            views concatenated in the views' order (e.g. keyframes best retrieved
            first).
        distances: [K] each row's descriptor distance (any monotone measure).

    Returns:
        int64 row indices, one per distinct query keypoint, in keypoint order: the
        row with the smallest distance, a tie going to the earlier row (the earlier
        view).
    """
    query_indices = np.asarray(query_indices, dtype=np.int64).reshape(-1)
    distances = np.asarray(distances).reshape(-1)
    if len(query_indices) != len(distances):
        raise DataError(
            f"{len(query_indices)} query indices but {len(distances)} distances; one of "
            "each per match"
        )
    if len(query_indices) == 0:
        return np.zeros(0, dtype=np.int64)
    # lexsort sorts by its last key first and is stable: by keypoint, then distance,
    # then (equal distances) by row, so the first row of each keypoint is its best.
    order = np.lexsort((distances, query_indices))
    first = np.ones(len(order), dtype=bool)
    first[1:] = query_indices[order[1:]] != query_indices[order[:-1]]
    return order[first]
