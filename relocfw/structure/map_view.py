"""One image of the map as the structure builders take it: pixels, pose, camera, depth."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.core.imaging import check_rgb_image
from relocfw.core.rigid import checked_rigid
from relocfw.core.values import Pose


@dataclass(frozen=True, eq=False)
class MapView:
    """A map image with everything the structure builders need to know about it.

    Attributes:
        image: [H, W, 3] uint8 RGB (relocfw.core.imaging.read_rgb reads one); H and W
            must be the camera's height and width, since keypoints are measured in
            the camera's pixels.
        pose: camera-to-world Pose (metres, quaternion w first).
        camera: intrinsics of `image` (undistorted pinhole).
        depth_path: a 16-bit PNG of depth in millimetres (7-Scenes' `.depth.png`,
            relocfw.data.depth.read_depth) covering the image's field of view, or None
            when the view has none (build_by_triangulation never reads it).
        name: how reports and errors name the view (e.g. `seq-01/frame-000000`).
        depth_units_per_metre: what one metre is stored as in the depth PNG: 1000
            (millimetres: 7-Scenes, the synthetic scene), 5000 (TUM RGB-D), as
            relocfw.data.frames.Frame.depth_units_per_metre.
        depth_camera: the depth sensor's intrinsics at the depth map's resolution, or
            None: the depth map is registered to the image and read pixel for pixel
            (the map's aspect ratio must then be the image's). With a depth camera,
            the builders register the depth into the image's pixels first
            (relocfw.structure.registration.register_depth).
        depth_to_colour: [4, 4] rigid transform from depth to colour camera
            coordinates, used with `depth_camera`; None: the identity.

    The image is not copied (a map holds hundreds; copying each would double the
    memory); do not change it while the view is in use. Equality is identity
    (eq=False): comparing two views' pixels element-wise has no single truth value.

    Raises:
        DataError: naming the view when the image is not [H, W, 3] uint8 or its size
            is not the camera's, `pose` is not a Pose, `camera` not a PinholeCamera,
            `name` not a string, `depth_units_per_metre` not a positive number,
            `depth_camera` not a PinholeCamera or `depth_to_colour` not rigid.
    """

    image: np.ndarray
    pose: Pose
    camera: PinholeCamera
    depth_path: Path | None = None
    name: str = ""
    depth_units_per_metre: float = 1000.0
    depth_camera: PinholeCamera | None = None
    depth_to_colour: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise DataError(f"map view name must be a string, got {self.name!r}")
        label = f"map view {self.name!r}"
        check_rgb_image(self.image, label)
        if not isinstance(self.pose, Pose):
            raise DataError(f"{label}: pose must be a Pose, got {type(self.pose).__name__}")
        if not isinstance(self.camera, PinholeCamera):
            raise DataError(
                f"{label}: camera must be a PinholeCamera, got {type(self.camera).__name__}"
            )
        height, width = self.image.shape[:2]
        if (width, height) != (self.camera.width, self.camera.height):
            raise DataError(
                f"{label}: image is {width}x{height} but its camera is "
                f"{self.camera.width}x{self.camera.height}; pass camera.scaled_to({width}, "
                f"{height}) for a resized image"
            )
        if self.depth_path is not None:
            if not isinstance(self.depth_path, str | Path):
                raise DataError(
                    f"{label}: depth_path must be a path or None, got {self.depth_path!r}"
                )
            object.__setattr__(self, "depth_path", Path(self.depth_path))
        units = self.depth_units_per_metre
        number = isinstance(units, int | float | np.number) and not isinstance(units, bool)
        if not (number and math.isfinite(units) and units > 0):
            raise DataError(
                f"{label}: depth_units_per_metre must be a positive number (1000 for "
                f"millimetres), got {units!r}"
            )
        object.__setattr__(self, "depth_units_per_metre", float(units))
        if self.depth_camera is not None and not isinstance(self.depth_camera, PinholeCamera):
            raise DataError(
                f"{label}: depth_camera must be a PinholeCamera or None, got "
                f"{type(self.depth_camera).__name__}"
            )
        if self.depth_to_colour is not None:
            rigid = checked_rigid(self.depth_to_colour, f"{label}: depth_to_colour")
            object.__setattr__(self, "depth_to_colour", rigid)

    def __repr__(self) -> str:
        # The pixels' shape, not the pixels (the default would print the whole image).
        return (
            f"MapView(name={self.name!r}, image={self.image.shape}, "
            f"position={self.pose.position.round(3).tolist()}, depth_path={self.depth_path})"
        )
