"""The frozen values passed between pipeline stages."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch


@dataclass(frozen=True)
class Crop:
    """A square window of the original image, in pixels of the original image."""

    x: int
    y: int
    size: int


def on_one_hemisphere(quaternion: np.ndarray) -> np.ndarray:
    """The one of q and -q (the same rotation) with w > 0, or, where w = 0, whose first
    non-zero component is positive.

    A pose regressor's loss compares quaternions as 4-vectors, so q and -q would be
    two different targets for one rotation; trajectories from SLAM systems (ORB-SLAM2,
    Eigen) flip sign freely. Every `Pose` is put on this hemisphere when it is made.
    """
    q = np.asarray(quaternion, dtype=np.float64)
    nonzero = np.flatnonzero(q)
    if len(nonzero) and q[nonzero[0]] < 0:
        return -q
    return q


@dataclass(frozen=True)
class Pose:
    """Camera-to-world pose: position in metres, unit quaternion (w, x, y, z).

    Convention: the quaternion is kept on one hemisphere (`on_one_hemisphere`: w > 0),
    so q and -q, which are the same rotation, become the same pose.
    """

    position: np.ndarray
    quaternion: np.ndarray

    def __post_init__(self) -> None:
        # Copies as float64 so a caller's later edits cannot change a frozen pose.
        position = np.array(self.position, dtype=np.float64).reshape(3)
        quaternion = on_one_hemisphere(np.array(self.quaternion, dtype=np.float64).reshape(4))
        position.setflags(write=False)
        quaternion.setflags(write=False)
        object.__setattr__(self, "position", position)
        object.__setattr__(self, "quaternion", quaternion)

    @property
    def is_finite(self) -> bool:
        """Whether every number of the pose is finite: a network or a file may give
        NaN, which every distance to it would silently carry."""
        return bool(np.isfinite(self.position).all() and np.isfinite(self.quaternion).all())


@dataclass(frozen=True)
class PoseOutput:
    """What a backbone returns for a batch of network inputs.

    Attributes:
        positions: [B, 3] positions in metres (world frame).
        quaternions: [B, 4] unit quaternions, w first.
        features: [B, D] image descriptors used for similarity.
        auxiliary: extra (positions, quaternions) pairs from auxiliary heads, used only
            by the training loss; empty when the backbone has none.
        position_spread: [B] uncertainty in metres (sqrt of the trace of the position
            covariance) when the backbone samples (Bayesian PoseNet), else None.
        orientation_spread_deg: [B] mean angle of the samples from the mean rotation.
    """

    positions: torch.Tensor
    quaternions: torch.Tensor
    features: torch.Tensor
    auxiliary: tuple[tuple[torch.Tensor, torch.Tensor], ...] = field(default=())
    position_spread: torch.Tensor | None = None
    orientation_spread_deg: torch.Tensor | None = None


@dataclass(frozen=True)
class Localization:
    """The answer for one query image."""

    pose: Pose
    crop: Crop
    distance: float  # descriptor distance of the chosen crop to the map
    evaluations: int  # distinct crops scored
    seconds: float
    position_spread: float = float("nan")  # Bayesian uncertainty (m), NaN when not sampled
    orientation_spread_deg: float = float("nan")
    # Network cost in whole-input passes; None: one per crop scored (scoring=plain).
    network_passes: float | None = None
    # The refiner's (relocfw.core.refinement): its confidence (e.g. PnP inliers; NaN
    # without one), whether it fell back to the network's pose, its time per part.
    refine_confidence: float = float("nan")
    fell_back: bool = False
    refine_seconds: dict[str, float] = field(default_factory=dict)
    # Calibrated error bounds (relocfw.core.error_bounds): the answer's position error
    # (map units) and orientation error (deg) stay below these for the model's stated
    # coverage of answers like it; inf: the validation answers like it give no finite
    # bound (too few, or too many failed); NaN: the model has no calibrated bounds.
    position_bound: float = float("nan")
    orientation_bound_deg: float = float("nan")

    def __post_init__(self) -> None:
        if self.network_passes is None:
            object.__setattr__(self, "network_passes", float(self.evaluations))


@dataclass(frozen=True)
class CropWithPose(Crop):
    """A crop search's choice that carries the pose to answer with, instead of the
    chosen crop's own network pose: e.g. a blend of every window's pose
    (relocfw.plugins.window_rule_crop). The crop stays the window the answer is
    reported on, and a refiner starts from `pose`."""

    pose: Pose | None = None

    def plain(self) -> Crop:
        return Crop(self.x, self.y, self.size)
