"""refine=retrieval: the image-retrieval baseline, the poses of the nearest map images.

The query's answer is the distance-weighted mean pose of the `k` map images whose
descriptors are nearest to the chosen crop's descriptor, instead of the network's pose.
The refiner keeps its own z-scored copy of the map's descriptors, standardised exactly
as index=exhaustive standardises them, so it works beside any index (the index serves
the crop search) and finds the neighbours index=exhaustive would (the older query option
`retrieval_k` needed index=exhaustive).

Memory: that copy is float64, N x D x 8 bytes (a 700-image map of 1280-d EfficientNet
descriptors: 7 MB; 10^6 x 2048: 16 GB), searched exhaustively, beside whatever the
index keeps. For maps of 10^5 images and more this refiner is not built for the scale
(retrieving through index=faiss's approximate neighbours would be; not written yet).

Confidence: minus the z-scored descriptor distance to the nearest map image, so higher
is more trustworthy (0 is a query that looks exactly like a map image). It never falls
back: there is always a nearest map image.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import ClassVar

import numpy as np
import torch
from threadpoolctl import ThreadpoolController

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import mean_quaternion
from relocfw.core.options import integer_at_least
from relocfw.core.refinement import MapImage, PoseRefiner, Refined, RefineQuery
from relocfw.core.standardise import ZScore, check_features, k_nearest
from relocfw.core.values import Pose

# Added to every distance before it is inverted into a weight: a query that equals a
# map image gets (nearly) all the weight instead of a division by zero.
WEIGHT_EPSILON = 1e-6


class RetrievalRefiner(PoseRefiner):
    """The distance-weighted mean pose of the `k` map images nearest to the query.

    Args:
        k: map images averaged; each weighs 1 / (its descriptor distance + 1e-6),
            normalised (k=1: the nearest map image's pose).
    """

    replaces_network_pose: ClassVar[bool] = True

    def __init__(self, k: int = 1) -> None:
        self.k = integer_at_least("refine.k", k, 1)
        self._threadpools: ThreadpoolController | None = None

    def fit(self, views: Sequence[MapImage], descriptors: np.ndarray, quiet: bool = True) -> None:
        features = check_features(descriptors)
        if len(views) != len(features):
            raise DataError(f"fit: {len(views)} map images but {len(features)} descriptors")
        self.zscore = ZScore().fit(features)
        self.points = self.zscore(features)
        self.poses = [view.pose for view in views]

    def refine(self, query: RefineQuery) -> Refined:
        if not hasattr(self, "points"):
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        started = time.perf_counter()
        features = check_features(np.asarray(query.descriptor)[None], self.points.shape[1])
        # A query's lookup is small: a multi-threaded BLAS call would leave its workers
        # spinning, competing with the network for the cores (relocfw.core.scorer).
        with self.one_blas_thread():
            distances, indices = k_nearest(self.zscore(features), self.points, self.k)
        pose = weighted_mean_pose([self.poses[i] for i in indices[0]], distances[0])
        seconds = {"retrieval": time.perf_counter() - started}
        return Refined(pose, confidence=-float(distances[0, 0]), fell_back=False, seconds=seconds)

    def one_blas_thread(self):  # noqa: ANN201 - threadpoolctl's context manager
        if self._threadpools is None:
            self._threadpools = ThreadpoolController()
        return self._threadpools.limit(limits=1, user_api="blas")

    def state(self) -> dict[str, torch.Tensor]:
        """The standardisation, the standardised map descriptors and the map poses
        (float64, so a loaded refiner answers to the last digit)."""
        if not hasattr(self, "points"):
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        poses = [[*p.position, *p.quaternion] for p in self.poses]
        return {
            **self.zscore.state(),
            # k too: a caller who saves without the refiner's options still gets it back.
            "k": torch.tensor(self.k),
            "points": torch.from_numpy(self.points),
            "poses": torch.tensor(poses, dtype=torch.float64).reshape(-1, 7),
        }

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """What `state` returned; also index=exhaustive's state plus the map poses,
        which is how a model file written before refine=retrieval is read. A state
        that is not that (a model file is data from anyone) is a DataError naming the
        key, before anything is kept."""
        points = finite_matrix(state, "points")
        poses = finite_matrix(state, "poses")
        if poses.shape[1] != 7 or len(poses) != len(points):
            raise DataError(
                f"retrieval state: {len(points)} map descriptors but poses of shape "
                f"{tuple(poses.shape)} (expected [{len(points)}, 7])"
            )
        for key in ("mean", "std"):
            column = state.get(key)
            if not isinstance(column, torch.Tensor) or column.shape != (points.shape[1],):
                raise DataError(
                    f"retrieval state: {key} must be a tensor of {points.shape[1]} values "
                    f"(one per descriptor dimension), got {describe(column)}"
                )
        k = self.k
        if "k" in state:  # absent from an index=exhaustive state (older model files)
            stored = state["k"]
            if not isinstance(stored, torch.Tensor) or stored.numel() != 1:
                raise DataError(f"retrieval state: k must be one integer, got {describe(stored)}")
            k = integer_at_least("refine.k", stored.item(), 1)
        self.zscore = ZScore().load_state(state)
        self.k = k
        self.points = points
        self.poses = [Pose(row[:3], row[3:]) for row in poses]


def finite_matrix(state: dict[str, torch.Tensor], key: str) -> np.ndarray:
    """state[key] as a 2-D float64 array of finite numbers, or a DataError naming key."""
    value = state.get(key)
    if not isinstance(value, torch.Tensor) or value.ndim != 2:
        raise DataError(f"retrieval state: {key} must be a 2-D tensor, got {describe(value)}")
    array = value.double().numpy()
    if not np.isfinite(array).all():
        raise DataError(f"retrieval state: {key} holds NaN or infinite values")
    return array


def describe(value: object) -> str:
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {tuple(value.shape)}"
    return "nothing" if value is None else type(value).__name__


def weighted_mean_pose(poses: Sequence[Pose], distances: np.ndarray) -> Pose:
    """The mean of `poses` weighted by 1 / (distance + 1e-6), normalised; the
    quaternions averaged by Markley's method (relocfw.core.geometry.mean_quaternion)."""
    weights = 1.0 / (np.asarray(distances, dtype=np.float64) + WEIGHT_EPSILON)
    weights /= weights.sum()
    position = np.sum([w * p.position for w, p in zip(weights, poses, strict=True)], axis=0)
    quaternion = mean_quaternion(np.stack([p.quaternion for p in poses]), weights)
    return Pose(position, quaternion)
