"""Lifting image keypoints to 3-D world points with a depth map.

Conventions: the camera frame is OpenCV's and 7-Scenes' (x right, y down, z forward);
depth is the z coordinate of the surface point in that frame (not the distance along
the ray), as Kinect depth maps store it; poses are camera-to-world
(relocfw.core.values.Pose): world = R camera + position.
"""

from __future__ import annotations

import numpy as np

from relocfw.core.arrays import point_rows
from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.core.geometry import quaternion_to_matrix
from relocfw.core.values import Pose


def depth_pixel_indices(
    keypoints: np.ndarray, camera: PinholeCamera, depth_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest depth pixel of each keypoint.

    The depth map is taken to cover the image's field of view at its own resolution,
    so coordinates scale by the size ratio with pixel edges on pixel edges:
    x_depth = (x + 0.5) * W_depth / W_image - 0.5 (as relocfw.core.camera.scaled_to).

    Args:
        keypoints: [N, 2] float64 pixel (x, y) in the camera's image.
        camera: the camera of the image the keypoints come from.
        depth_shape: (H, W) of the depth map.

    Returns:
        rows [N] int64, columns [N] int64 (0 where outside) and inside [N] bool.
    """
    height, width = depth_shape
    x = (keypoints[:, 0] + 0.5) * (width / camera.width) - 0.5
    y = (keypoints[:, 1] + 0.5) * (height / camera.height) - 0.5
    # floor(v + 0.5): pixel j covers [j - 0.5, j + 0.5); np.rint would round halves
    # to even, sending x.5 left or right depending on j.
    columns = np.floor(x + 0.5).astype(np.int64)
    rows = np.floor(y + 0.5).astype(np.int64)
    inside = (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    return np.where(inside, rows, 0), np.where(inside, columns, 0), inside


def lift_keypoints(
    keypoints: np.ndarray, depth: np.ndarray, camera: PinholeCamera, camera_to_world: Pose
) -> np.ndarray:
    """World points of keypoints, at the depth of their nearest depth-map pixel.

    Each keypoint's ray goes through its exact (sub-pixel) coordinate; only the depth
    is read at the nearest pixel, so a point projected into the image and lifted back
    with its own depth returns to where it was.

    Args:
        keypoints: [N, 2] pixel (x, y) in the image `camera` describes (if features
            came from a resized image, pass `camera.scaled_to(its size)`).
        depth: [H, W] depth in metres (z in the camera frame), NaN or <= 0 where
            there is no reading (relocfw.data.depth.read_depth); its resolution may
            differ from the image's.
        camera: intrinsics of the keypoints' image.
        camera_to_world: the image's camera-to-world pose.

    Returns:
        [N, 3] float64 world points in metres; NaN rows where the depth is missing,
        not positive, or the keypoint falls outside the depth map.

    Raises:
        DataError: when `keypoints` is not an [N, 2] array of finite numbers or
            `depth` is not a 2-D array of real numbers.
    """
    points = point_rows(keypoints, "keypoints", 2)
    try:
        depth = np.asarray(depth)
    except ValueError:  # ragged nested lists
        raise DataError("depth must be an [H, W] array of metres") from None
    if depth.ndim != 2 or depth.dtype.kind not in "fiu" or 0 in depth.shape:
        raise DataError(
            f"depth must be a non-empty [H, W] array of metres, got shape {depth.shape} "
            f"of {depth.dtype}"
        )
    rows, columns, inside = depth_pixel_indices(points, camera, depth.shape)
    z = depth[rows, columns].astype(np.float64)
    # Missing readings are NaN already when read_depth made the map; a raw 0 is
    # caught here too, so no point lands on the camera centre.
    valid = inside & np.isfinite(z) & (z > 0)
    z = np.where(valid, z, np.nan)
    in_camera = np.stack(
        [(points[:, 0] - camera.cx) / camera.fx * z, (points[:, 1] - camera.cy) / camera.fy * z, z],
        axis=1,
    )
    rotation = quaternion_to_matrix(camera_to_world.quaternion)
    return in_camera @ rotation.T + camera_to_world.position
