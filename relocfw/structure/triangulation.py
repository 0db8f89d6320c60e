"""Two-view triangulation of matched keypoints, with the checks that make a point usable.

cv2.triangulatePoints (linear DLT) finds a point for any pair of rays, even rays that
miss each other, point away from a camera or are nearly parallel. A point is kept
only if it is in front of both cameras, reprojects close to both keypoints, and the
rays meet at an angle wide enough to fix its depth (at a small angle a pixel of noise
moves the point metres along the rays).

Conventions: camera frame x right, y down, z forward; poses camera-to-world
(relocfw.core.values.Pose); pixel coordinates as relocfw.core.camera.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from relocfw.core.arrays import point_rows
from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import quaternion_to_matrix
from relocfw.core.values import Pose


def world_to_camera(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """(R [3, 3], t [3]) with camera = R world + t, from a camera-to-world pose."""
    rotation = quaternion_to_matrix(pose.quaternion).T
    return rotation, -rotation @ pose.position


def checked_pixels(points: np.ndarray, name: str) -> np.ndarray:
    """`points` as [N, 2] float64 of finite numbers, or a DataError naming it."""
    return point_rows(points, name, 2)


def checked_bound(name: str, value: float, low: float, high: float) -> float:
    """`value` as a float in [low, high), or a ConfigError naming it."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if not (math.isfinite(number) and low <= number < high):
        raise ConfigError(f"{name} must be in [{low:g}, {high:g}), got {value!r}")
    return number


def triangulate(
    points_a: np.ndarray,
    points_b: np.ndarray,
    camera_a: PinholeCamera,
    pose_a: Pose,
    camera_b: PinholeCamera,
    pose_b: Pose,
    max_reprojection_px: float = 4.0,
    min_angle_deg: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """World points of keypoints matched between two images of known pose.

    Args:
        points_a: [N, 2] pixel (x, y) in image a.
        points_b: [N, 2] pixel (x, y) in image b; row i matches row i of `points_a`.
        camera_a: intrinsics of image a.
        pose_a: camera-to-world pose of image a.
        camera_b: intrinsics of image b.
        pose_b: camera-to-world pose of image b.
        max_reprojection_px: the largest reprojection error allowed in either image,
            in pixels (> 0).
        min_angle_deg: the smallest angle between the two rays at the point, in
            degrees, in [0, 180).

    Returns:
        points: [N, 3] float64 world points in metres; NaN rows where not valid, so an
            unchecked point cannot be used by mistake.
        valid: [N] bool, True where the point is in front of both cameras,
            reprojects within `max_reprojection_px` in both images and its rays
            meet at `min_angle_deg` or more.

    Raises:
        DataError: when the point arrays are not [N, 2] of finite numbers or differ
            in length.
        ConfigError: naming `max_reprojection_px` or `min_angle_deg` when out of range.
    """
    a = checked_pixels(points_a, "points_a")
    b = checked_pixels(points_b, "points_b")
    if len(a) != len(b):
        raise DataError(f"points_a has {len(a)} rows, points_b {len(b)}; they must pair up")
    max_error = checked_bound("max_reprojection_px", max_reprojection_px, 0.0, math.inf)
    if max_error <= 0:
        raise ConfigError(f"max_reprojection_px must be above 0, got {max_reprojection_px!r}")
    min_angle = checked_bound("min_angle_deg", min_angle_deg, 0.0, 180.0)
    if len(a) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)

    rotation_a, translation_a = world_to_camera(pose_a)
    rotation_b, translation_b = world_to_camera(pose_b)
    projection_a = camera_a.matrix() @ np.column_stack([rotation_a, translation_a])
    projection_b = camera_b.matrix() @ np.column_stack([rotation_b, translation_b])
    homogeneous = cv2.triangulatePoints(projection_a, projection_b, a.T.copy(), b.T.copy())

    # A last coordinate of (near) zero is a point at infinity: parallel rays.
    w = homogeneous[3]
    finite = np.abs(w) > 1e-12 * np.abs(homogeneous[:3]).max(axis=0).clip(min=1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        points = (homogeneous[:3] / np.where(finite, w, 1.0)).T

    in_a = points @ rotation_a.T + translation_a
    in_b = points @ rotation_b.T + translation_b
    in_front = finite & (in_a[:, 2] > 0) & (in_b[:, 2] > 0)
    # project() gives NaN behind a camera; NaN compares False, so those fail here too.
    with np.errstate(invalid="ignore"):
        error_a = np.linalg.norm(camera_a.project(in_a) - a, axis=1)
        error_b = np.linalg.norm(camera_b.project(in_b) - b, axis=1)
        reprojects = (error_a <= max_error) & (error_b <= max_error)

    # The angle at the point between the rays from the two camera centres.
    ray_a = points - pose_a.position
    ray_b = points - pose_b.position
    norms = np.linalg.norm(ray_a, axis=1) * np.linalg.norm(ray_b, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cosine = np.clip(np.sum(ray_a * ray_b, axis=1) / norms, -1.0, 1.0)
        angle = np.degrees(np.arccos(cosine))
        wide = angle >= min_angle

    valid = in_front & reprojects & wide
    points[~valid] = np.nan
    return points, valid
