"""The pose stage's plugin interface: the final pose from the network's answer.

The fourth extension point after Backbone, SimilarityIndex and CropSearch. A
`PoseRefiner` is fitted once on the map images (their images, poses, cameras, depth
maps and network descriptors) and then, per query, turns the network's answer for the
chosen crop into the final pose: e.g. local features of the query matched against
keyframes of the map and an absolute pose solved from them (relocfw.plugins
.features_refiner, the structure-based family hloc belongs to). A refiner that cannot
do better (too few inliers) answers the network's pose and says it fell back, so a
report can count it and a robot can distrust it.

Without a refiner (`Relocalizer(refiner=None)`, `refine=none`) the network's pose is
the answer, as before this stage existed. The image-retrieval baseline is a refiner too
(relocfw.plugins.retrieval_refiner, `refine=retrieval`): it answers with the poses of
the map images nearest to the chosen crop's descriptor.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from relocfw.core.camera import PinholeCamera
from relocfw.core.observations import PointObservations
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
        observations: the 3-D points a reconstruction saw in the image (a COLMAP
            model's, relocfw.data.frames.Frame.observations), None where none.
        depth_camera: the depth sensor's intrinsics where the depth map is not
            registered to the image (7-Scenes' raw Kinect depth); None: read it pixel
            for pixel with the image (relocfw.data.frames.Frame.depth_camera).
        depth_to_colour: [4, 4] rigid transform from depth to colour camera
            coordinates, with `depth_camera`; None: the identity.
        pose_to_colour: [4, 4] rigid transform from the coordinates of the sensor
            `pose` describes to the colour camera's (relocfw.core.sensor_poses);
            None: `pose` is the colour camera's.
    """

    name: str
    image: np.ndarray
    pose: Pose
    camera: PinholeCamera | None = None
    depth_path: Path | None = None
    depth_units_per_metre: float = 1000.0
    observations: PointObservations | None = None
    depth_camera: PinholeCamera | None = None
    depth_to_colour: np.ndarray | None = None
    pose_to_colour: np.ndarray | None = None


@dataclass(frozen=True)
class RefineQuery:
    """What the pipeline knows of a query when the refiner runs.

    Attributes:
        image: H x W x 3 uint8 RGB, the whole query image (not the crop).
        network_pose: the pose the pipeline would answer without a refiner.
        descriptor: [D] the chosen crop's dropout-free descriptor, comparable with the
            map descriptors given to `fit` (keyframes can be retrieved with it).
        camera: the query's intrinsics; None: the map's camera (the same robot).
        name: the query's frame name where the caller knows it (e.g.
            "seq-03/frame-000042"); a refiner that needs the frames before the query
            (refine=sequence) reads its recording from the folder part.
    """

    image: np.ndarray
    network_pose: Pose
    descriptor: np.ndarray
    camera: PinholeCamera | None = None
    name: str | None = None


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

    # True for a refiner whose answer never uses the network's pose (retrieval answers
    # with map images' poses). Sampling the network's pose (query.crop_samples,
    # backbone.mc_samples) would then be wasted work whose spread describes a pose
    # nobody answers with, so the pipeline refuses that combination.
    replaces_network_pose: ClassVar[bool] = False

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

    def reset(self) -> None:  # noqa: B027 - optional hook, no-op default
        """Forget what earlier queries left (a refiner that reads a query's recording
        keeps its frames): `evaluate` calls it before its timed pass, after the untimed
        warm-up query. The default keeps no per-query state."""

    def check_map(self, frames: Sequence[object]) -> None:  # noqa: B027 - optional hook
        """Raise ConfigError if this refiner cannot use these map images.

        Called with the training split's frames (relocfw.data.frames.Frame: `name`,
        `camera`, `depth_path`, ...) before training, so a map the refiner cannot use
        (e.g. no camera intrinsics) fails in a second rather than after the model is
        trained. The default accepts any map.
        """

    def state(self) -> dict[str, torch.Tensor]:
        """The fitted refiner as tensors, for model files; optional for plugins.

        Everything the refiner's queries use, as plain tensors (a model file is read
        by torch's weights-only loader: no other objects, no pickle), e.g.
        refine=features' map structure (relocfw.structure.map_state), so a loaded model
        needs no map image. A refiner without it is left out of a model file (whose
        model then answers with the network's pose).
        """
        raise NotImplementedError(f"{type(self).__name__} cannot be saved in a model file")

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """Restore what `state` returned: the refiner is then fitted. The state comes
        from a file anyone may have written: check every tensor's dtype, shape and
        values before use and raise DataError naming the one at fault."""
        raise NotImplementedError(f"{type(self).__name__} cannot be loaded from a model file")

    @property
    def saves_state(self) -> bool:
        """True when the refiner defines `state` and `load_state` (model files keep it)."""
        cls = type(self)
        return cls.state is not PoseRefiner.state and cls.load_state is not PoseRefiner.load_state
