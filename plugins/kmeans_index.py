"""The paper's map: k-means centres of standardised training descriptors."""

from __future__ import annotations

import numpy as np
import torch
from sklearn.cluster import KMeans

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.interfaces import SimilarityIndex
from relocfw.core.options import integer_at_least
from relocfw.core.standardise import ZScore, check_features, finite_rows, nearest


class KMeansIndex(SimilarityIndex):
    """Distance of a descriptor to the nearest of k cluster centres.

    Args:
        k: number of clusters; at most the number of training descriptors.
        seed: seeds k-means++ initialisation, so a map is reproducible.
        n_init: k-means restarts; the best (lowest inertia) is kept.
    """

    def __init__(self, k: int = 40, seed: int = 0, n_init: int = 4) -> None:
        self.k = integer_at_least("k", k, 1)
        self.seed = integer_at_least("seed", seed, 0)
        self.n_init = integer_at_least("n_init", n_init, 1)

    def check_map_size(self, count: int) -> None:
        if self.k > count:
            raise ConfigError(
                f"k={self.k} is more clusters than training descriptors ({count}); "
                f"choose k <= {count}"
            )

    def fit(self, features: np.ndarray) -> None:
        features = check_features(features)
        self.check_map_size(len(features))
        self.zscore = ZScore().fit(features)
        kmeans = KMeans(n_clusters=self.k, n_init=self.n_init, random_state=self.seed)
        kmeans.fit(self.zscore(features))
        self.centres = kmeans.cluster_centers_

    def state(self) -> dict[str, torch.Tensor]:
        return {**self.zscore.state(), "centres": torch.from_numpy(self.centres)}

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """What `state` returned; a DataError naming the key for anything else (NaN
        centres would make every distance NaN)."""
        zscore = ZScore().load_state(state)
        self.centres = finite_rows(state, "centres", len(zscore.mean))
        self.zscore = zscore

    @property
    def dim(self) -> int:
        """The descriptors' dimensions (after fit or load_state)."""
        return self.centres.shape[1]

    def assign(self, features: np.ndarray) -> np.ndarray:
        """Cluster of each descriptor (for plots of the map)."""
        features = check_features(features, self.centres.shape[1])
        return nearest(self.zscore(features), self.centres)[1]

    def distance(self, features: np.ndarray) -> np.ndarray:
        if not hasattr(self, "centres"):
            raise DataError("the index is not fitted yet: call fit() first")
        features = check_features(features, self.centres.shape[1])
        return nearest(self.zscore(features), self.centres)[0]
