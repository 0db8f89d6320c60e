"""Depth registered to the colour camera: a depth sensor's map redrawn in the colour image's pixels.

An RGB-D camera such as the Kinect v1 has two sensors a few centimetres apart with
different lenses (7-Scenes: depth focal length 585 px, colour 525 px, 2.5 cm apart
along x). Reading the raw depth map at a colour keypoint's pixel takes the depth of
another surface point: up to tens of pixels off near the border (the focal lengths
differ) and a parallax of several pixels at 1-2 m (the offset). Registration moves
every depth reading to where the colour camera sees it, so a keypoint reads the depth
of its own surface point.

Conventions as relocfw.structure.lifting: camera frames x right, y down, z forward;
depth is z in its camera's frame (not the distance along the ray), in metres;
`depth_to_colour` is the 4x4 rigid transform x_colour = R x_depth + t.
"""

from __future__ import annotations

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.core.rigid import checked_rigid, transform_points


def register_depth(
    depth_m: np.ndarray,
    depth_camera: PinholeCamera,
    colour_camera: PinholeCamera,
    depth_to_colour: np.ndarray | None = None,
) -> np.ndarray:
    """The depth map as the colour camera would have measured it, in its pixel grid.

    Every valid depth pixel is lifted with the depth camera (through its pixel's
    centre), moved into the colour camera's frame and projected; it lands on the
    colour pixel nearest to its projection, with its z in the colour frame. Where
    several readings land on one colour pixel the nearest (smallest z) wins, as the
    colour camera sees the front surface: a z-buffer. Colour pixels that no reading
    reaches stay NaN (outside the depth sensor's view, occluded from it, or between
    readings where the depth camera samples more coarsely than the colour camera).

    Args:
        depth_m: [H_d, W_d] depth in metres at the depth camera's resolution; NaN,
            infinite or <= 0 where there is no reading (relocfw.data.depth.read_depth).
        depth_camera: the depth sensor's intrinsics; its size must be the map's.
        colour_camera: the colour image's intrinsics; the result has its size.
        depth_to_colour: [4, 4] rigid transform from depth to colour camera
            coordinates; None: the identity (the cameras share a centre and axes).

    Returns:
        [colour_camera.height, colour_camera.width] float32 depth in metres, NaN where
        no reading lands.

    Raises:
        DataError: when `depth_m` is not a 2-D array of numbers of the depth camera's
            size, a camera is not a PinholeCamera, or `depth_to_colour` is not rigid
            (relocfw.core.rigid.checked_rigid).
    """
    for name, camera in (("depth_camera", depth_camera), ("colour_camera", colour_camera)):
        if not isinstance(camera, PinholeCamera):
            raise DataError(f"{name} must be a PinholeCamera, got {type(camera).__name__}")
    depth = np.asarray(depth_m)
    if depth.ndim != 2 or depth.dtype.kind not in "fiu":
        raise DataError(f"depth must be an [H, W] array of metres, got {depth.shape} {depth.dtype}")
    if depth.shape != (depth_camera.height, depth_camera.width):
        raise DataError(
            f"depth map is {depth.shape[1]}x{depth.shape[0]} but its depth camera is "
            f"{depth_camera.width}x{depth_camera.height}"
        )
    transform = (
        np.eye(4) if depth_to_colour is None else checked_rigid(depth_to_colour, "depth_to_colour")
    )
    z = depth.astype(np.float64)
    rows, columns = np.nonzero(np.isfinite(z) & (z > 0))
    z = z[rows, columns]
    in_depth = np.column_stack(
        [
            (columns - depth_camera.cx) / depth_camera.fx * z,
            (rows - depth_camera.cy) / depth_camera.fy * z,
            z,
        ]
    )
    in_colour = transform_points(transform, in_depth)
    front = in_colour[:, 2] > 0
    in_colour = in_colour[front]
    pixels = colour_camera.project(in_colour)
    # floor(v + 0.5): the pixel whose square holds the projection (as lifting reads it).
    target_columns = np.floor(pixels[:, 0] + 0.5).astype(np.int64)
    target_rows = np.floor(pixels[:, 1] + 0.5).astype(np.int64)
    inside = (
        (target_columns >= 0)
        & (target_columns < colour_camera.width)
        & (target_rows >= 0)
        & (target_rows < colour_camera.height)
    )
    flat = target_rows[inside] * colour_camera.width + target_columns[inside]
    # The z-buffer without a Python loop: an unbuffered minimum per target pixel
    # (np.minimum.at applies every reading, repeated pixels included).
    nearest = np.full(colour_camera.height * colour_camera.width, np.inf)
    np.minimum.at(nearest, flat, in_colour[inside, 2])
    nearest[np.isinf(nearest)] = np.nan
    return nearest.astype(np.float32).reshape(colour_camera.height, colour_camera.width)
