"""A synthetic world of textured planar quads, rendered with exact depth.

The structure tests need images whose 3-D truth is known to the millimetre: each
pixel's ray is cast against a few textured rectangles (a back wall, a side wall, a
floor and a panel standing in front, for parallax), the nearest hit is coloured by
bilinear texture lookup at twice the resolution and area-averaged down (no
aliasing, so SIFT finds the same corners in every view), and the depth (z in the
camera frame) of each pixel centre is exact.

Conventions as relocfw.core.camera: camera x right, y down, z forward; pixel (x, y)
measured from the centre of the top-left pixel; poses camera-to-world.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.geometry import matrix_to_quaternion, quaternion_to_matrix
from relocfw.core.values import Pose

TEXELS_PER_METRE = 256
BACKGROUND = 128  # grey where a ray hits nothing: no texture, no keypoint


@dataclass(frozen=True, eq=False)
class Quad:
    """A textured rectangle: corner + s u + t v for s in [0, width], t in [0, height].

    Attributes:
        corner: [3] world position of the texture's (0, 0) corner, metres.
        u: [3] unit direction of the texture's x axis.
        v: [3] unit direction of its y axis, orthogonal to u.
        width: extent along u, metres.
        height: extent along v, metres.
        texture: [h, w, 3] uint8, TEXELS_PER_METRE texels per metre.
    """

    corner: np.ndarray
    u: np.ndarray
    v: np.ndarray
    width: float
    height: float
    texture: np.ndarray


def make_texture(rng: np.random.Generator, width_m: float, height_m: float) -> np.ndarray:
    """A texture with structure at many scales: smooth colour noise at three scales,
    random discs and rectangles (corners and blobs for SIFT) and fine noise."""
    width = int(width_m * TEXELS_PER_METRE)
    height = int(height_m * TEXELS_PER_METRE)
    texture = np.full((height, width, 3), 128.0, dtype=np.float32)
    for cell, weight in ((64, 50.0), (16, 35.0), (4, 20.0)):
        coarse = rng.normal(0, 1, (height // cell + 2, width // cell + 2, 3)).astype(np.float32)
        texture += weight * cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    for _ in range(int(40 * width_m * height_m)):
        colour = rng.uniform(0, 255, 3).tolist()
        x, y = int(rng.uniform(0, width)), int(rng.uniform(0, height))
        size = int(rng.uniform(0.02, 0.12) * TEXELS_PER_METRE)
        if rng.random() < 0.5:
            cv2.circle(texture, (x, y), size, colour, thickness=-1, lineType=cv2.LINE_AA)
        else:
            cv2.rectangle(
                texture, (x, y), (x + size, y + int(size * rng.uniform(0.5, 2))), colour, -1
            )
    texture += rng.normal(0, 6, (height, width, 1)).astype(np.float32)
    return np.clip(texture, 0, 255).astype(np.uint8)


def make_world(seed: int = 0) -> list[Quad]:
    """A room corner in front of cameras at the origin looking along +z (y down):
    a back wall at z = 3.2 m, a left wall at x = -1.6 m, a floor at y = 1.1 m and a
    panel at z = 2.2 m."""
    rng = np.random.default_rng(seed)
    x, y, z = np.eye(3)

    def quad(
        corner: list[float], u: np.ndarray, v: np.ndarray, width: float, height: float
    ) -> Quad:
        return Quad(np.array(corner, float), u, v, width, height, make_texture(rng, width, height))

    return [
        quad([-1.6, -1.4, 3.2], x, y, 3.6, 2.5),  # back wall, facing -z
        quad([-1.6, -1.4, 0.5], z, y, 2.7, 2.5),  # left wall, facing +x
        quad([-1.6, 1.1, 0.5], x, z, 3.6, 2.7),  # floor, facing -y (up)
        quad([0.1, -0.6, 2.2], x, y, 0.7, 0.9),  # a panel in front of the back wall
    ]


def cast(
    world: list[Quad], origin: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of each ray.

    Args:
        world: the quads.
        origin: [3] the rays' common origin.
        directions: [N, 3] directions (any length; t is in their units).

    Returns:
        t [N] (inf where nothing is hit), quad index [N] (-1 there) and the hit's
        texture coordinates s [N], t [N] in metres along the quad's u and v.
    """
    count = len(directions)
    nearest = np.full(count, np.inf)
    which = np.full(count, -1)
    along_u = np.zeros(count)
    along_v = np.zeros(count)
    for index, q in enumerate(world):
        normal = np.cross(q.u, q.v)
        offset = origin - q.corner
        # Per ray only scalars ([N] vectors): hit = origin + t d, so its texture
        # coordinates are offset.u + t d.u and offset.v + t d.v.
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(offset @ normal) / (directions @ normal)
            s = offset @ q.u + t * (directions @ q.u)
            r = offset @ q.v + t * (directions @ q.v)
            hit = (
                np.isfinite(t)
                & (t > 1e-6)
                & (t < nearest)
                & (s >= 0)
                & (s <= q.width)
                & (r >= 0)
                & (r <= q.height)
            )
        nearest = np.where(hit, t, nearest)
        which = np.where(hit, index, which)
        along_u = np.where(hit, s, along_u)
        along_v = np.where(hit, r, along_v)
    return nearest, which, along_u, along_v


def pixel_rays(camera: PinholeCamera, pose: Pose, pixels: np.ndarray) -> np.ndarray:
    """[N, 3] world directions of pixels' rays, scaled so their camera z is 1 (then a
    ray's t is the depth of its hit)."""
    in_camera = np.column_stack(
        [
            (pixels[:, 0] - camera.cx) / camera.fx,
            (pixels[:, 1] - camera.cy) / camera.fy,
            np.ones(len(pixels)),
        ]
    )
    return in_camera @ quaternion_to_matrix(pose.quaternion).T


def grid(camera: PinholeCamera) -> np.ndarray:
    """[H * W, 2] pixel centres (x, y), row by row."""
    x, y = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
    return np.column_stack([x.ravel(), y.ravel()])


def render(
    world: list[Quad], pose: Pose, camera: PinholeCamera, supersample: int = 2
) -> np.ndarray:
    """[H, W, 3] uint8 RGB image of the world from a camera-to-world pose."""
    fine = camera.scaled_to(camera.width * supersample, camera.height * supersample)
    _, which, along_u, along_v = cast(world, pose.position, pixel_rays(fine, pose, grid(fine)))
    image = np.full((fine.height * fine.width, 3), BACKGROUND, dtype=np.float32)
    for index, q in enumerate(world):
        mask = which == index
        if not mask.any():
            continue
        # Texel (i, j) is centred at ((j + 0.5), (i + 0.5)) / TEXELS_PER_METRE metres.
        # Whole-image maps: cv2.remap takes maps of at most 32767 rows or columns.
        shape = (fine.height, fine.width)
        map_x = (along_u * TEXELS_PER_METRE - 0.5).astype(np.float32).reshape(shape)
        map_y = (along_v * TEXELS_PER_METRE - 0.5).astype(np.float32).reshape(shape)
        sampled = cv2.remap(
            q.texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
        ).reshape(-1, 3)[mask]
        image[mask] = sampled.reshape(-1, 3)
    image = image.reshape(fine.height, fine.width, 3)
    small = cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return np.clip(np.rint(small), 0, 255).astype(np.uint8)


def depth_map(world: list[Quad], pose: Pose, camera: PinholeCamera) -> np.ndarray:
    """[H, W] float32 depth (camera z) in metres at each pixel centre; NaN where the
    ray hits nothing."""
    t, which, _, _ = cast(world, pose.position, pixel_rays(camera, pose, grid(camera)))
    depth = np.where(which >= 0, t, np.nan).astype(np.float32)
    return depth.reshape(camera.height, camera.width)


def surface_points(
    world: list[Quad], pose: Pose, camera: PinholeCamera, pixels: np.ndarray
) -> np.ndarray:
    """[N, 3] world points the rays of sub-pixel `pixels` hit (NaN where none): the
    truth a keypoint's 3-D point should have."""
    t, which, _, _ = cast(world, pose.position, pixel_rays(camera, pose, pixels))
    points = pose.position + pixel_rays(camera, pose, pixels) * t[:, None]
    points[which < 0] = np.nan
    return points


def write_depth_png(depth: np.ndarray, path: Path, units_per_metre: float = 1000.0) -> Path:
    """Write a depth map in metres as a 16-bit PNG (0: no reading), in millimetres as
    7-Scenes stores it, or other units (TUM: 5000 per metre); returns the path."""
    units = np.where(np.isfinite(depth), np.rint(depth * units_per_metre), 0)
    if not cv2.imwrite(str(path), units.astype(np.uint16)):
        raise OSError(f"cannot write {path}")
    return path


def looking_at(position: list[float], target: list[float]) -> Pose:
    """Camera-to-world pose at `position` looking at `target`, image y pointing down
    (world +y, the floor's side)."""
    centre = np.array(position, float)
    forward = np.array(target, float) - centre
    forward /= np.linalg.norm(forward)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return Pose(centre, matrix_to_quaternion(np.column_stack([right, down, forward])))
