"""Exact nearest-neighbour map: distance to the closest training descriptor."""

from __future__ import annotations

import numpy as np
import torch

from relocfw.core.errors import DataError
from relocfw.core.interfaces import SimilarityIndex
from relocfw.core.standardise import ZScore, check_features, finite_rows, k_nearest


class ExhaustiveIndex(SimilarityIndex):
    """Keeps every standardised training descriptor; the exact baseline for k-means."""

    def fit(self, features: np.ndarray) -> None:
        features = check_features(features)
        self.zscore = ZScore().fit(features)
        self.points = self.zscore(features)

    def state(self) -> dict[str, torch.Tensor]:
        return {**self.zscore.state(), "points": torch.from_numpy(self.points)}

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """What `state` returned; a DataError naming the key for anything else (NaN
        points would make every distance NaN)."""
        zscore = ZScore().load_state(state)
        self.points = finite_rows(state, "points", len(zscore.mean))
        self.zscore = zscore

    @property
    def dim(self) -> int:
        """The descriptors' dimensions (after fit or load_state)."""
        return self.points.shape[1]

    def neighbours(self, features: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """[n, k] distances to and indices of the nearest training descriptors.

        The same neighbours refine=retrieval (relocfw.plugins.retrieval_refiner) finds:
        it standardises the map's descriptors as this index does.
        """
        if not hasattr(self, "points"):
            raise DataError("the index is not fitted yet: call fit() first")
        features = check_features(features, self.points.shape[1])
        return k_nearest(self.zscore(features), self.points, k)

    def nearest(self, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance to and index of the nearest training descriptor."""
        distances, indices = self.neighbours(features, 1)
        return distances[:, 0], indices[:, 0]

    def distance(self, features: np.ndarray) -> np.ndarray:
        return self.nearest(features)[0]
