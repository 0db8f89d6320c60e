"""A structure map from RGB-D map images: each keypoint lifted with its depth,
registered into the colour image where the view has a depth camera."""

from __future__ import annotations

import sys
from collections.abc import Sequence

import numpy as np

from relocfw.core.errors import DataError
from relocfw.core.options import integer_at_least
from relocfw.core.progress import Progress
from relocfw.data.depth import (
    PLAUSIBLE_MEDIAN_DEPTH_M,
    check_depth_range,
    median_depth,
    read_depth,
)
from relocfw.structure.features import checked_image_scale, extract_rootsift
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.map_view import MapView
from relocfw.structure.registration import register_depth
from relocfw.structure.structure_map import SkippedView, StructureMap, on_descriptor_grid
from relocfw.structure.view_features import checked_view, checked_views

# A depth map may have another resolution than its image when it covers the same
# field of view: scaled to the image's width, its height may be off by this much.
ASPECT_TOLERANCE_PX = 1.0


def depth_of_view(view: MapView) -> tuple[np.ndarray | None, str]:
    """The view's depth map in metres, in its image's pixels, or (None, why not).

    A view with a depth camera has its depth registered into the image first
    (relocfw.structure.registration.register_depth), so each keypoint reads the depth
    of its own surface point; without one, the map is read as registered already.

    Missing, unreadable and corrupt files are a reason to skip the view (one bad
    frame of a recording should not stop a map of thousands); a depth map whose
    size is not its depth camera's, or (without a depth camera) whose aspect ratio
    differs from the image's, or whose median depth is implausible in metres
    (relocfw.data.depth.check_depth_range: a wrong depth_units_per_metre), is a
    DataError. (build_from_depth judges the scale over the whole map instead.)
    """
    depth, reason = raw_depth(view)
    if depth is None:
        return None, reason
    check_depth_range(depth, view.depth_path, view.depth_units_per_metre)
    return in_image_pixels(view, depth), ""


def raw_depth(view: MapView) -> tuple[np.ndarray | None, str]:
    """The view's depth map in metres as its file holds it, or (None, why not): no
    depth_path, or a missing, unreadable or corrupt file (read_depth's message)."""
    if view.depth_path is None:
        return None, "no depth map (depth_path is None)"
    try:
        return read_depth(view.depth_path, None, view.depth_units_per_metre), ""
    except DataError as error:
        return None, str(error)


def in_image_pixels(view: MapView, depth: np.ndarray) -> np.ndarray:
    """A depth map of the view in its image's pixels: registered from its depth
    camera, or as it is; a DataError naming the file when its size does not fit."""
    depth_height, depth_width = depth.shape
    if view.depth_camera is not None:
        sensor = view.depth_camera
        if (depth_width, depth_height) != (sensor.width, sensor.height):
            raise DataError(
                f"{view.depth_path}: depth map is {depth_width}x{depth_height} but the depth "
                f"camera of {view.name!r} is {sensor.width}x{sensor.height}"
            )
        return register_depth(depth, sensor, view.camera, view.depth_to_colour)
    # The depth map's height if it were scaled to the image's width.
    scaled_height = depth_height * view.camera.width / depth_width
    if abs(scaled_height - view.camera.height) > ASPECT_TOLERANCE_PX:
        raise DataError(
            f"{view.depth_path}: depth map is {depth_width}x{depth_height} but its image "
            f"({view.name!r}) is {view.camera.width}x{view.camera.height}; a depth map of "
            "another size must have the image's aspect ratio (it is taken to cover the "
            "same field of view)"
        )
    return depth


class DepthScale:
    """The depth scale judged over the map, not per frame.

    A wrong depth_units_per_metre puts every frame's median far outside
    PLAUSIBLE_MEDIAN_DEPTH_M; one frame of a camera facing a wall (a median of a few
    cm) does not. So the median of the frames' medians decides: outside the range,
    the map's depth is at a wrong scale and the build stops (as soon as more than half
    the map's frames lie on one side, which settles that median); a single frame
    outside it only loses its depth, with one note naming it.
    """

    def __init__(self, frames: int) -> None:
        self.frames = frames
        self.medians: list[float] = []
        self.low: list[MapView] = []  # frames below the range, in order
        self.high: list[MapView] = []

    def plausible(self, view: MapView, median: float | None) -> bool:
        """Record the frame's median depth (`median_depth`); whether it is plausible
        in metres.

        Raises:
            DataError: once the map's median depth is settled outside the range.
        """
        if median is None:
            return True  # no reading at all: the build reports that view as skipped
        self.medians.append(median)
        low, high = PLAUSIBLE_MEDIAN_DEPTH_M
        side = self.low if median < low else self.high if median > high else None
        if side is None:
            return True
        side.append(view)
        if len(side) > self.frames / 2:
            self.refuse()
        return False

    def finish(self) -> None:
        """Raises the DataError when the map's median depth is implausible."""
        low, high = PLAUSIBLE_MEDIAN_DEPTH_M
        if self.medians and not low <= float(np.median(self.medians)) <= high:
            self.refuse()

    def refuse(self) -> None:
        median = float(np.median(self.medians))
        first = (self.high if median > PLAUSIBLE_MEDIAN_DEPTH_M[1] else self.low)[0]
        try:
            check_depth_range(np.array([median]), first.depth_path, first.depth_units_per_metre)
        except DataError as error:
            raise DataError(
                f"{error} (the map's median depth: the median of the medians of the "
                f"{len(self.medians)} depth maps read; the first outside the range named)"
            ) from None


def depth_judged(view: MapView, scale: DepthScale) -> tuple[np.ndarray | None, str]:
    """As `depth_of_view`, with the depth scale judged over the map (`scale`, one per
    map, `finish`ed after its last frame): a frame whose own median is implausible in a
    plausible map gives (None, why), said once on stderr."""
    depth, reason = raw_depth(view)
    if depth is None:
        return None, reason
    return judged_depth(view, depth, scale)


def judged_depth(
    view: MapView, depth: np.ndarray, scale: DepthScale
) -> tuple[np.ndarray | None, str]:
    """`depth_judged` of a depth map already read (`raw_depth`)."""
    median = median_depth(depth)
    if not scale.plausible(view, median):
        return None, implausible_frame(view, median)
    return in_image_pixels(view, depth), ""


def implausible_frame(view: MapView, median: float) -> str:
    """Why a frame of a plausible map loses its depth, said once on stderr (printed
    even when quiet, as a cache note is: it changes the map)."""
    low, high = PLAUSIBLE_MEDIAN_DEPTH_M
    reason = (
        f"median depth {median:.3g} m in {view.depth_path}, outside "
        f"{low:g}-{high:g} m while the map's is within: its depth is left out"
    )
    print(f"note: map image {view.name!r}: {reason}", file=sys.stderr)
    return reason


def build_from_depth(
    views: Sequence[MapView],
    max_features: int = 1024,
    quiet: bool = False,
    image_scale: float = 1.0,
) -> StructureMap:
    """The structure of RGB-D map images: RootSIFT keypoints lifted with their depth.

    Each view's depth map (relocfw.data.depth.read_depth, in the view's
    depth_units_per_metre) gives each keypoint the depth of its nearest depth pixel
    (relocfw.structure.lifting.lift_keypoints). A view with a depth camera has its
    depth registered into the image's pixels first (depth_of_view); without one, a
    depth map of another resolution than the image is scaled to it when the aspect
    ratios agree.

    Policy for views without usable depth: the view is kept with its features and
    all-NaN points (queries may still match it; those matches give no
    correspondence) and listed in `skipped_views` with the reason: no depth_path,
    a missing, corrupt or non-16-bit file (read_depth's message, naming it), a
    median depth outside PLAUSIBLE_MEDIAN_DEPTH_M in a map whose depth is plausible
    (one note on stderr names it), no depth reading at any keypoint, or no
    keypoints at all.

    Each view is read once, in order, so `views` may be a lazy sequence that loads
    its images on access.

    Args:
        views: the map images (M of them), each with pose, camera and depth_path.
        max_features: the most keypoints per image (>= 1), strongest first.
        quiet: show no progress bar.
        image_scale: the share of each side SIFT runs at, in (0, 1]
            (features.extract_rootsift; keypoints stay in the image's pixels).

    Returns:
        StructureMap with source "depth"; descriptors on the stored uint8 grid.

    Raises:
        DataError: naming the view when an entry is not a MapView or its pose is not
            finite; naming the depth file when its aspect ratio is not the image's;
            naming a depth file when the map's depth is implausible in metres (a
            wrong depth scale, judged over the map: DepthScale).
        ConfigError: when `max_features` is not an integer >= 1.
    """
    checked_views(views)
    max_features = integer_at_least("max_features", max_features, 1)
    image_scale = checked_image_scale(image_scale)
    features, points, poses, cameras, names, skipped = [], [], [], [], [], []
    progress = Progress(len(views), "map structure from depth", quiet=quiet)
    scale = DepthScale(len(views))
    for number in range(len(views)):
        view = checked_view(number, views[number])
        found = on_descriptor_grid(extract_rootsift(view.image, max_features, image_scale))
        depth, reason = depth_judged(view, scale)
        if depth is None:
            lifted = np.full((len(found), 3), np.nan, dtype=np.float32)
        else:
            lifted = lift_keypoints(found.keypoints, depth, view.camera, view.pose)
            if len(found) == 0:
                reason = "no keypoints (an image without texture)"
            elif not np.isfinite(lifted).all(axis=1).any():
                reason = f"no keypoint has a depth reading in {view.depth_path}"
        if reason:
            skipped.append(SkippedView(view.name, reason))
        features.append(found)
        points.append(lifted)
        poses.append(view.pose)
        cameras.append(view.camera)
        names.append(view.name)
        progress.advance()
    progress.close()
    scale.finish()
    return StructureMap(
        features=tuple(features),
        points=tuple(points),
        poses=tuple(poses),
        cameras=tuple(cameras),
        names=tuple(names),
        source="depth",
        skipped_views=tuple(skipped),
    )
