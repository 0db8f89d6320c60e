"""The pinhole camera: intrinsics of an undistorted image, checked once when made.

Conventions (OpenCV's, and 7-Scenes'): the camera frame has x to the right, y down
and z forward (the viewing direction); a pixel coordinate (x, y) is measured from the
centre of the top-left pixel, so pixel (i, j) of an image array covers
[j - 0.5, j + 0.5] x [i - 0.5, i + 0.5]. Lens distortion is not modelled: 7-Scenes'
colour images are used undistorted, as every method on it does.

The camera lives in the core (not relocfw.structure) because relocfw.data reads it
from files and may import only the core (tests/core/test_layout.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from relocfw.core.arrays import point_rows
from relocfw.core.errors import ConfigError

# What a stored camera (a map's, a model file's) may hold: no real image is wider or
# taller than MOST_CAMERA_PIXELS, no lens has a focal length above MOST_FOCAL_PIXELS
# (a 1000 mm lens on 1 um pixels), and a principal point lies near its image (within
# one image size of it: a calibrated image's is inside it). A stored camera beyond
# these is refused on loading, naming the file and the key, instead of failing every
# query (cx = 1e300) or being taken for the query's fault (width = 1e15).
MOST_CAMERA_PIXELS = 100_000
MOST_FOCAL_PIXELS = 1_000_000
CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")


def implausible_camera_keys(rows: np.ndarray) -> dict[str, np.ndarray]:
    """For each of CAMERA_KEYS, which of the [M, 6] rows (fx, fy, cx, cy, width,
    height) hold an implausible value there (see MOST_CAMERA_PIXELS); vectorised, as a
    building's map holds 10^5 cameras."""
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 6)
    # Comparisons with NaN are False, so every rule is written as "is good", negated.
    with np.errstate(invalid="ignore", over="ignore"):
        sizes = rows[:, 4:]
        good_size = (sizes >= 1) & (sizes <= MOST_CAMERA_PIXELS) & (sizes == np.floor(sizes))
        good_focal = (rows[:, :2] > 0) & (rows[:, :2] <= MOST_FOCAL_PIXELS)
        centre = rows[:, 2:4]
        good_centre = (centre >= -sizes) & (centre <= 2 * sizes) & np.isfinite(centre)
    good = np.concatenate([good_focal, good_centre, good_size], axis=1)
    return {key: ~good[:, column] for column, key in enumerate(CAMERA_KEYS)}


def camera_fault(rows: np.ndarray) -> tuple[int, str] | None:
    """The first implausible camera of [M, 6] rows and what is wrong with it (naming the
    key), or None when every row is a plausible camera."""
    faults = implausible_camera_keys(rows)
    bad = np.logical_or.reduce(list(faults.values()))
    if not bad.any():
        return None
    number = int(np.flatnonzero(bad)[0])
    key = next(key for key in CAMERA_KEYS if faults[key][number])
    value = float(np.asarray(rows, dtype=np.float64).reshape(-1, 6)[number, CAMERA_KEYS.index(key)])
    if key in ("fx", "fy"):
        rule = f"a focal length above 0 and at most {MOST_FOCAL_PIXELS:g} px"
    elif key in ("width", "height"):
        rule = f"a whole number of pixels from 1 to {MOST_CAMERA_PIXELS:g}"
    else:
        size = "width" if key == "cx" else "height"
        rule = f"within one {size} of the image (-{size} to 2 x {size})"
    return number, f"{key} {value:g} must be {rule}"


def positive_size(name: str, value: object) -> int:
    """`value` as a positive int (bools and fractions refused), or a ConfigError naming it."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ConfigError(f"{name} must be a positive integer number of pixels, got {value!r}")
    if value <= 0:
        raise ConfigError(f"{name} must be a positive number of pixels, got {value}")
    return int(value)


def finite_number(name: str, value: object) -> float:
    """`value` as a finite float, or a ConfigError naming it."""
    if isinstance(value, bool):
        raise ConfigError(f"{name} must be a number, got {value!r}")
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    return number


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of a pinhole camera for images of `width` x `height` pixels.

    Attributes:
        fx: focal length along x, in pixels (> 0).
        fy: focal length along y, in pixels (> 0).
        cx: principal point x, in pixels from the centre of the top-left pixel.
        cy: principal point y, in pixels.
        width: image width in pixels (> 0).
        height: image height in pixels (> 0).

    Raises:
        ConfigError: naming the first value that is not finite, not positive (focal
            lengths, sizes) or not an integer (sizes).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        # Stored as plain floats and ints so equal cameras compare and hash equal,
        # whatever numpy scalar types the caller passed.
        for name in ("fx", "fy"):
            value = finite_number(f"camera {name}", getattr(self, name))
            if value <= 0:
                raise ConfigError(f"camera {name} must be a positive focal length, got {value}")
            object.__setattr__(self, name, value)
        for name in ("cx", "cy"):
            object.__setattr__(self, name, finite_number(f"camera {name}", getattr(self, name)))
        for name in ("width", "height"):
            object.__setattr__(self, name, positive_size(f"camera {name}", getattr(self, name)))

    def matrix(self) -> np.ndarray:
        """The calibration matrix K.

        Returns:
            [3, 3] float64: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
        """
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def scaled_to(self, width: int, height: int) -> PinholeCamera:
        """The intrinsics of this camera's image resized to `width` x `height`.

        Resizing (cv2.resize, torch's interpolate with align_corners=False) maps pixel
        edges onto pixel edges, so a coordinate measured from the top-left pixel's
        centre maps as x' = (x + 0.5) * sx - 0.5; scaling cx alone by sx would shift
        the principal point by half a pixel of the change.

        Args:
            width: the new width in pixels (> 0).
            height: the new height in pixels (> 0).

        Returns:
            A new PinholeCamera; the aspect ratio may change (fx and fy scale apart).

        Raises:
            ConfigError: naming `width` or `height` when it is not a positive integer.
        """
        width = positive_size("width", width)
        height = positive_size("height", height)
        sx = width / self.width
        sy = height / self.height
        return PinholeCamera(
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=width,
            height=height,
        )

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """Pixel coordinates of points given in the camera frame.

        Args:
            points_camera: [N, 3] points (x right, y down, z forward), any unit.

        Returns:
            [N, 2] float64 pixel (x, y). Points with z <= 0 (on or behind the camera
            plane) have no image and give NaN rather than a plausible wrong pixel.
            Points in front of the camera but outside the image are projected as they
            are (coordinates beyond [0, width) x [0, height)).

        Raises:
            DataError: when `points_camera` is not an [N, 3] array.
        """
        # NaN rows are allowed: they project to NaN, as points behind the camera do.
        points = point_rows(points_camera, "points_camera", 3, finite=False)
        z = points[:, 2]
        in_front = z > 0
        # Divide only where z > 0 so no division-by-zero warning escapes.
        safe_z = np.where(in_front, z, 1.0)
        pixels = np.stack(
            [self.fx * points[:, 0] / safe_z + self.cx, self.fy * points[:, 1] / safe_z + self.cy],
            axis=1,
        )
        pixels[~in_front] = np.nan
        return pixels


# Microsoft 7-Scenes' two Kinect v1 sensors, 640 x 480 each. The dataset's page and
# the camera-intrinsics.txt that its copies ship give one calibration, focal length
# 585 and principal point (320, 240): the DEPTH sensor's. The colour sensor is
# another camera: the scene-coordinate pipelines on 7-Scenes (DSAC*, ACE:
# datasets/setup_7scenes.py, after tsattler/visloc_pseudo_gt_limitations) give it
# a nominal focal length of 525 with the same principal point. On the shared Red
# Kitchen frames, points triangulated between colour images agree in range with
# registered depth near 525, not at 585 (benchmarks/depth_registration.py;
# docs/structure.md, "Colour and depth cameras"). 532 was tried (dataset.colour_focal)
# and not taken: docs/results/structure.md, "The colour camera's focal length".
SEVENSCENES_COLOUR = PinholeCamera(525.0, 525.0, 320.0, 240.0, 640, 480)
SEVENSCENES_DEPTH = PinholeCamera(585.0, 585.0, 320.0, 240.0, 640, 480)
# The name this module gave the 585 camera before the two sensors were told apart;
# kept for code that imports it, with the value it always had (the depth camera's).
SEVENSCENES_DEFAULT = SEVENSCENES_DEPTH
