"""A textured 3-D room, rendered by ray casting with a pinhole camera.

Real projective geometry, so that the image a pose produces is the one the camera
would see: walls, floor, ceiling and a few boxes (furniture that gives parallax), each
face with its own procedural texture so places are distinguishable, as in a real room.
World frame: z up, metres. Camera frame: x right, y down, z forward (as 7-Scenes).

The camera has 7-Scenes' field of view: focal length 585/640 of the image width on
both axes, principal point at the image centre; `RoomRenderer.camera` gives its
intrinsics and `RoomRenderer.depth` the z of every pixel's hit, so a depth map and
the colour image describe the same rays.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from relocfw.core.camera import PinholeCamera

TEXELS_PER_METRE = 48
# The Kinect's horizontal field of view, as 7-Scenes' 585 px for 640 px images.
FOCAL_PER_WIDTH = 585.0 / 640.0


@dataclass(frozen=True)
class Box:
    """Axis-aligned box, lower and upper corners in metres."""

    low: tuple[float, float, float]
    high: tuple[float, float, float]


@dataclass(frozen=True)
class Room:
    """The room's extent and the boxes standing in it."""

    size: tuple[float, float, float] = (8.0, 6.0, 3.0)
    boxes: tuple[Box, ...] = (
        Box((3.3, 2.5, 0.0), (4.7, 3.5, 1.1)),
        Box((0.2, 0.2, 0.0), (1.0, 1.4, 1.9)),
        Box((6.6, 4.4, 0.0), (7.8, 5.8, 0.8)),
        Box((6.9, 0.2, 0.0), (7.8, 0.9, 2.2)),
    )


def make_texture(rng: np.random.Generator, width_m: float, height_m: float) -> np.ndarray:
    """A face texture: a base colour, random rectangles and discs, fine noise.

    Large shapes make places recognisable from afar; the noise gives the network
    high-frequency structure to hold on to, as real surfaces do.
    """
    w = max(8, int(width_m * TEXELS_PER_METRE))
    h = max(8, int(height_m * TEXELS_PER_METRE))
    base = rng.uniform(60, 200, size=3)
    texture = np.empty((h, w, 3), dtype=np.float32)
    texture[:] = base
    area = width_m * height_m
    for _ in range(int(6 + 5 * area)):
        colour = rng.uniform(0, 255, size=3).tolist()
        x0, y0 = int(rng.uniform(0, w)), int(rng.uniform(0, h))
        if rng.random() < 0.5:
            x1 = x0 + int(rng.uniform(0.1, 0.8) * TEXELS_PER_METRE)
            y1 = y0 + int(rng.uniform(0.1, 0.8) * TEXELS_PER_METRE)
            cv2.rectangle(texture, (x0, y0), (x1, y1), colour, thickness=-1)
        else:
            radius = int(rng.uniform(0.05, 0.4) * TEXELS_PER_METRE)
            cv2.circle(texture, (x0, y0), radius, colour, thickness=-1)
    texture += rng.normal(0, 12, size=(h, w, 1)).astype(np.float32)
    return np.clip(texture, 0, 255).astype(np.uint8)


class RoomRenderer:
    """Renders RGB images of a room from camera-to-world poses."""

    def __init__(self, room: Room, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.room = room
        # One texture per face: room faces first (x-, x+, y-, y+, z-, z+), then boxes.
        self.boxes = [Box((0.0, 0.0, 0.0), room.size), *room.boxes]
        self.textures = []
        for box in self.boxes:
            extent = np.subtract(box.high, box.low)
            for axis in range(3):
                u_axis, v_axis = [a for a in range(3) if a != axis]
                for _side in range(2):
                    self.textures.append(make_texture(rng, extent[u_axis], extent[v_axis]))

    @staticmethod
    def camera(width: int, height: int) -> PinholeCamera:
        """The intrinsics of a `width` x `height` image that `render` makes.

        Pixel (i, j) is the ray through (j + 0.5 - W/2, i + 0.5 - H/2) / f in a frame
        whose origin is the image's top-left corner, so in relocfw's convention
        (coordinates from the top-left pixel's centre) the principal point is
        ((W - 1) / 2, (H - 1) / 2). Supersampling does not change it: area-averaging
        s x s blocks maps pixel edges onto pixel edges.
        """
        focal = FOCAL_PER_WIDTH * width
        return PinholeCamera(focal, focal, width / 2 - 0.5, height / 2 - 0.5, width, height)

    def render(
        self, camera_to_world: np.ndarray, width: int, height: int, supersample: int = 2
    ) -> np.ndarray:
        """RGB uint8 image (height x width x 3) seen from the pose.

        Rendered at `supersample` times the size and area-averaged down, which removes
        the aliasing a point-sampled texture would otherwise show.
        """
        sw, sh = width * supersample, height * supersample
        origin, directions = self._rays(camera_to_world, sw, sh)
        nearest, face = self._hit(origin, directions)
        colour = self._colour(origin, directions, nearest, face)
        image = colour.reshape(sh, sw, 3)
        return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)

    def depth(self, camera_to_world: np.ndarray, width: int, height: int) -> np.ndarray:
        """The depth map of the image `render` makes from the same pose.

        One ray through each pixel's centre, not supersampled: averaging the depths of
        sub-pixels would invent surfaces between a box and the wall behind it.

        Args:
            camera_to_world: [4, 4] pose (camera x right, y down, z forward).
            width, height: the image size in pixels.

        Returns:
            [height, width] float64 z of each pixel's hit in the camera frame, in
            metres: the distance along the optical axis, not along the ray. Every ray
            from inside the room hits a face, so every value is finite.
        """
        origin, directions = self._rays(camera_to_world, width, height)
        nearest, _ = self._hit(origin, directions)
        # The rays have z = 1 in the camera frame, so the ray parameter of a hit is
        # its z: the point is origin + t * R @ ray, and R^T (point - origin) = t * ray.
        return nearest.reshape(height, width)

    @staticmethod
    def _rays(
        camera_to_world: np.ndarray, width: int, height: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The camera centre [3] and one world ray per pixel [H*W, 3], row-major.

        Each ray is R @ (x / f, y / f, 1) for the pixel's centre (x, y) from the image
        centre, so its camera-frame z is 1 (not unit length).
        """
        focal = FOCAL_PER_WIDTH * width
        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        rays = np.stack([(u - width / 2) / focal, (v - height / 2) / focal, np.ones_like(u)], -1)
        directions = rays.reshape(-1, 3) @ camera_to_world[:3, :3].T
        return camera_to_world[:3, 3], directions

    def _hit(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nearest hit of each ray: its parameter t [N] and face id [N].

        Face ids: box index * 6 + axis * 2 + side, box 0 the room itself.
        """
        n = len(directions)
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = 1.0 / directions
        nearest = np.full(n, np.inf)
        face = np.zeros(n, dtype=np.int64)
        # The room is seen from inside: the exit point of its box.
        room = self.boxes[0]
        t_far = (
            np.stack(
                [
                    np.where(inverse[:, a] > 0, room.high[a], room.low[a]) - origin[a]
                    for a in range(3)
                ],
                -1,
            )
            * inverse
        )
        axis = np.argmin(t_far, axis=1)
        nearest = t_far[np.arange(n), axis]
        face = axis * 2 + (directions[np.arange(n), axis] > 0)
        # Boxes are seen from outside: the entry point (slab method).
        for index, box in enumerate(self.boxes[1:], start=1):
            t_low = (np.array(box.low) - origin) * inverse
            t_high = (np.array(box.high) - origin) * inverse
            t_enter_axes = np.minimum(t_low, t_high)
            t_enter = t_enter_axes.max(axis=1)
            t_exit = np.maximum(t_low, t_high).min(axis=1)
            hit = (t_enter < t_exit) & (t_enter > 1e-6) & (t_enter < nearest)
            enter_axis = np.argmax(t_enter_axes, axis=1)
            nearest = np.where(hit, t_enter, nearest)
            side = directions[np.arange(n), enter_axis] < 0  # hit the upper face
            face = np.where(hit, index * 6 + enter_axis * 2 + side, face)
        return nearest, face

    def _colour(
        self, origin: np.ndarray, directions: np.ndarray, nearest: np.ndarray, face: np.ndarray
    ) -> np.ndarray:
        """RGB uint8 [N, 3] of each ray's hit: the face's texture, lit and faded."""
        n = len(directions)
        points = origin + directions * nearest[:, None]
        colour = np.zeros((n, 3), dtype=np.float32)
        for face_id in np.unique(face):
            mask = face == face_id
            colour[mask] = self._shade(int(face_id), points[mask], nearest[mask])
        return np.clip(colour, 0, 255).astype(np.uint8)

    def _shade(self, face_id: int, points: np.ndarray, distance: np.ndarray) -> np.ndarray:
        box = self.boxes[face_id // 6]
        axis = (face_id % 6) // 2
        u_axis, v_axis = [a for a in range(3) if a != axis]
        texture = self.textures[face_id]
        th, tw = texture.shape[:2]
        col = ((points[:, u_axis] - box.low[u_axis]) * TEXELS_PER_METRE).astype(np.int64)
        row = ((points[:, v_axis] - box.low[v_axis]) * TEXELS_PER_METRE).astype(np.int64)
        texels = texture[np.clip(row, 0, th - 1), np.clip(col, 0, tw - 1)].astype(np.float32)
        # A fixed light per axis and a little fall-off with distance, so faces read as 3-D.
        light = (0.75, 0.9, 1.0)[axis] * (0.85 + 0.15 * (face_id % 2))
        return texels * light * (1.0 / (1.0 + 0.03 * distance))[:, None]
