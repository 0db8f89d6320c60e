"""Poses of the colour camera where a dataset's poses describe another sensor.

A dataset's poses are those of one reference sensor. 7-Scenes' come from KinectFusion,
which tracked the Kinect's DEPTH sensor, while the images are the colour sensor's, 2.6
cm away along x and turned by about 0.65 degrees (relocfw.data.sevenscenes). A network
regressing poses does not care (it learns the dataset's poses from the images), but
geometry does: triangulating colour keypoints between map images, lifting registered
depth into the world, or solving a query's colour keypoints by PnP all need the pose
of the camera that took the image. With the depth sensor's pose in its place, each
map image's points are shifted by up to 2.6 cm in a direction that turns with the
image, and a solved pose is the colour camera's, 2.6 cm from what the dataset scores.

The structure refiners therefore work in colour-camera poses inside and answer in the
dataset's: `colour_pose` on the way in (map images, and a prior such as the network's
pose), `reference_pose` on the way out (the solved pose).

`pose_to_colour` is the 4x4 rigid transform x_colour = T x_reference from the
reference sensor's coordinates to the colour camera's (relocfw.core.rigid); None: the
poses are the colour camera's already.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import pose_from_matrix, pose_to_matrix
from relocfw.core.rigid import checked_rigid
from relocfw.core.values import Pose


def colour_pose(pose: Pose, pose_to_colour: np.ndarray | None) -> Pose:
    """The colour camera's camera-to-world pose given the reference sensor's.

    T_world_colour = T_world_reference T^-1. A pose that is not finite (a network's NaN)
    is returned as it is: there is no colour camera of no pose.
    """
    if pose_to_colour is None or not pose.is_finite:
        return pose
    inverse = np.linalg.inv(pose_to_colour)
    return pose_from_matrix(pose_to_matrix(pose) @ inverse, source="colour camera pose")


def reference_pose(pose: Pose, pose_to_colour: np.ndarray | None) -> Pose:
    """The reference sensor's pose given the colour camera's (colour_pose's inverse):
    T_world_reference = T_world_colour T."""
    if pose_to_colour is None or not pose.is_finite:
        return pose
    return pose_from_matrix(pose_to_matrix(pose) @ pose_to_colour, source="reference pose")


def map_pose_to_colour(views: Sequence[object], refiner: str) -> np.ndarray | None:
    """The one `pose_to_colour` of a map's images (anything with `name` and
    `pose_to_colour`, absent meaning None), checked rigid.

    Raises:
        ConfigError: naming the `refiner` and two images whose transforms differ: a
            query is answered in one frame, so the map's images must share it.
    """
    first = None
    found: np.ndarray | None = None
    for view in views:
        value = getattr(view, "pose_to_colour", None)
        transform = None if value is None else checked_rigid(value, f"{view.name}: pose_to_colour")
        if first is None:
            first, found = view, transform
            continue
        same = (found is None and transform is None) or (
            found is not None and transform is not None and np.allclose(found, transform)
        )
        if not same:
            raise ConfigError(
                f"{refiner}: map images {first.name} and {view.name} have different "
                "pose_to_colour transforms (which sensor their poses describe); a map's "
                "images must come from one camera rig"
            )
    return found


def in_colour_poses(views: Sequence, pose_to_colour: np.ndarray | None) -> list:
    """The map images (relocfw.core.refinement.MapImage) with their colour camera's
    poses in place of the dataset's (the same objects where `pose_to_colour` is None)."""
    if pose_to_colour is None:
        return list(views)
    return [replace(view, pose=colour_pose(view.pose, pose_to_colour)) for view in views]


# The model-file key of a fitted refiner's transform (absent: the poses are the
# colour camera's, as in every file written before the key existed).
STATE_KEY = "pose_to_colour"


def pose_to_colour_state(pose_to_colour: np.ndarray | None) -> dict[str, torch.Tensor]:
    """The transform as a model file keeps it: {STATE_KEY: [4, 4] float64}, or nothing."""
    if pose_to_colour is None:
        return {}
    return {STATE_KEY: torch.from_numpy(np.array(pose_to_colour, dtype=np.float64))}


def stored_pose_to_colour(state: dict[str, torch.Tensor], label: str) -> np.ndarray | None:
    """The transform a model file keeps (None without the key), checked rigid; a
    DataError naming `label` and the key otherwise (the file is data from anyone)."""
    if STATE_KEY not in state:
        return None
    value = state[STATE_KEY]
    if not isinstance(value, torch.Tensor) or value.dtype != torch.float64:
        raise DataError(f"{label}: {STATE_KEY} must be a float64 tensor")
    return checked_rigid(value.numpy(), f"{label}: {STATE_KEY}")
