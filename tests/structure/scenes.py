"""Synthetic geometry the structure tests share: random poses, points in view."""

from __future__ import annotations

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.geometry import quaternion_to_matrix
from relocfw.core.values import Pose


def random_pose(rng: np.random.Generator, spread: float = 1.0) -> Pose:
    """A camera-to-world pose with a uniformly random rotation (a normalised Gaussian
    4-vector is uniform on the rotations) and a position within `spread` metres."""
    quaternion = rng.normal(size=4)
    return Pose(rng.uniform(-spread, spread, 3), quaternion / np.linalg.norm(quaternion))


def to_camera(pose: Pose, world: np.ndarray) -> np.ndarray:
    """[N, 3] world points in the camera frame of a camera-to-world pose."""
    rotation = quaternion_to_matrix(pose.quaternion)
    return (np.asarray(world) - pose.position) @ rotation


def to_world(pose: Pose, in_camera: np.ndarray) -> np.ndarray:
    """[N, 3] camera-frame points in the world frame."""
    return np.asarray(in_camera) @ quaternion_to_matrix(pose.quaternion).T + pose.position


def points_in_view(
    rng: np.random.Generator,
    camera: PinholeCamera,
    pose: Pose,
    count: int,
    near: float = 1.0,
    far: float = 4.0,
) -> tuple[np.ndarray, np.ndarray]:
    """`count` world points seen by the camera: exact pixels [N, 2] uniform over the
    image and world points [N, 3] at depths (z) uniform in [near, far] metres."""
    pixels = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(count, 2))
    z = rng.uniform(near, far, count)
    in_camera = np.column_stack(
        [(pixels[:, 0] - camera.cx) / camera.fx * z, (pixels[:, 1] - camera.cy) / camera.fy * z, z]
    )
    return pixels, to_world(pose, in_camera)
