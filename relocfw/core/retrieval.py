"""The image-retrieval answer: the poses of the map images nearest to a descriptor."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from relocfw.core.errors import ConfigError
from relocfw.core.geometry import mean_quaternion
from relocfw.core.interfaces import SimilarityIndex
from relocfw.core.scorer import Scorer
from relocfw.core.values import Pose


def check_retrieval(index: SimilarityIndex, retrieval_k: int) -> None:
    """Retrieval answers with map images' poses: the index must name its neighbours."""
    if retrieval_k > 0 and not hasattr(index, "neighbours"):
        raise ConfigError(
            f"retrieval_k={retrieval_k} needs an index that returns neighbours "
            f"(index=exhaustive); {type(index).__name__} does not"
        )


def retrieved_pose(scorer: Scorer, map_poses: Sequence[Pose], features: np.ndarray, k: int) -> Pose:
    """The distance-weighted mean pose of the `k` map images nearest to [D] `features`."""
    with scorer.one_blas_thread():
        distances, indices = scorer.index.neighbours(features[None], k)
    weights = 1.0 / (distances[0] + 1e-6)
    weights /= weights.sum()
    poses = [map_poses[i] for i in indices[0]]
    position = np.sum([w * p.position for w, p in zip(weights, poses, strict=True)], axis=0)
    quaternion = mean_quaternion(np.stack([p.quaternion for p in poses]), weights)
    return Pose(position, quaternion)
