"""The pose stage's plugin interface: the final pose from the network's answer.

The fourth extension point after Backbone, SimilarityIndex and CropSearch. A
`PoseRefiner` is fitted once on the map images (their images, poses, cameras, depth
maps and network descriptors) and then, per query, turns the network's answer for the
chosen crop into the final pose: e.g. local features of the query matched against
keyframes of the map and an absolute pose solved from them (relocfw.plugins
.features_refiner, the structure-based family hloc belongs to). A refiner that cannot
do better (too few inliers) answers the network's pose and says it fell back, so a
report can count it and a robot can distrust it.

Without a refiner (`Relocalizer(refiner=None)`, `refine=none`) the network's pose, or
retrieval's with `retrieval_k`, is the answer, as before this stage existed.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.values import Pose


@dataclass(frozen=True)
class MapImage:
    """One map (training) image as a refiner sees it.

    Attributes:
        name: unique within the map, e.g. "seq-01/frame-000000" (names its files in
            messages).
        image: H x W x 3 uint8 RGB.
        pose: camera-to-world pose.
        camera: the image's pinhole intrinsics, None where the dataset has none.
        depth_path: its depth map (16-bit PNG of z along the optical axis, 0 = none),
            None if absent.
        depth_units_per_metre: the depth map's scale (1000: millimetres, as 7-Scenes;
            TUM RGB-D: 5000).
    """

    name: str
    image: np.ndarray
    pose: Pose
    camera: PinholeCamera | None = None
    depth_path: Path | None = None
    depth_units_per_metre: float = 1000.0


@dataclass(frozen=True)
class RefineQuery:
    """What the pipeline knows of a query when the refiner runs.

    Attributes:
        image: H x W x 3 uint8 RGB, the whole query image (not the crop).
        network_pose: the pose the pipeline would answer without a refiner.
        descriptor: [D] the chosen crop's dropout-free descriptor, comparable with the
            map descriptors given to `fit` (keyframes can be retrieved with it).
        camera: the query's intrinsics; None: the map's camera (the same robot).
    """

    image: np.ndarray
    network_pose: Pose
    descriptor: np.ndarray
    camera: PinholeCamera | None = None


@dataclass(frozen=True)
class Refined:
    """A refiner's answer.

    Attributes:
        pose: the final pose.
        confidence: how much to trust it, in the refiner's own unit (e.g. PnP inliers);
            higher is more trustworthy. NaN when the refiner has no such measure.
        fell_back: True when the refiner could not find a pose and `pose` is the
            network's: reports count these.
        seconds: time per part of the refinement (e.g. features, matching, solve).
    """

    pose: Pose
    confidence: float = float("nan")
    fell_back: bool = False
    seconds: Mapping[str, float] = field(default_factory=dict)


class PoseRefiner(ABC):
    """Turns the network's answer for the chosen crop into the final pose.

    Example:
        >>> class KeepNetworkPose(PoseRefiner):
        ...     def fit(self, views, descriptors, quiet=True):
        ...         pass
        ...     def refine(self, query):
        ...         return Refined(query.network_pose)
    """

    @abstractmethod
    def fit(self, views: Sequence[MapImage], descriptors: np.ndarray, quiet: bool = True) -> None:
        """Learn the map.

        Args:
            views: the map images, in the order of `descriptors`' rows.
            descriptors: [N, D] their centre crops' descriptors (what the index holds).
            quiet: no progress bars.
        """

    @abstractmethod
    def refine(self, query: RefineQuery) -> Refined:
        """The final pose of one query."""
