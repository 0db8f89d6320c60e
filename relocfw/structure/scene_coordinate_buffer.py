"""The training buffer of scene-coordinate regression: encoder cells sampled once.

ACE's idea: the frozen encoder runs once per map image and augmented pass, and a
random share of the cells it sees is kept (features + what each cell's target is);
the head then trains on random batches of that buffer for thousands of steps without
running the encoder again. Each cell keeps:

- its features ([C] float16: halves the buffer's memory; the head standardises them in
  float32);
- its pixel in the ORIGINAL map image (relocfw.structure.scene_coordinate_cells) and
  its map image's index, for the reprojection loss (RGB-only training);
- its world point where the map image has depth (NaN otherwise): depth registered
  into the colour camera (relocfw.structure.depth_structure, the same reading and the
  same map-wide judgement of the depth scale refine=features lifts keypoints with),
  read at the cell's pixel, lifted with the camera and the map pose. Cells without a
  depth reading are dropped in depth mode, so a frame whose median depth alone is
  implausible (a camera facing a wall) gives no cell, with one note naming it.

Per map image the buffer also keeps its camera (fx, fy, cx, cy) and world-to-camera
rotation and translation, which the reprojection loss needs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from relocfw.core.errors import DataError
from relocfw.core.geometry import quaternion_to_matrix
from relocfw.core.imaging import check_rgb_image
from relocfw.core.progress import Progress
from relocfw.core.refinement import MapImage
from relocfw.structure.depth_structure import DepthScale, judged_depth, raw_depth
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.map_view import MapView
from relocfw.structure.scene_coordinate_cells import (
    PLAIN,
    cell_pixels,
    encoder_input,
    random_jitter,
)

# An encoder: [1, 3, h, w] pixels in [0, 1] -> [1, C, h / 8, w / 8] features.
Encoder = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class BufferSettings:
    """How the buffer is sampled.

    Attributes:
        image_size: the encoder image's shorter side (refine.image_size).
        passes: encoder passes per map image, the first without augmentation.
        cells: the buffer's size (most cells kept, over all passes).
        scale_jitter: augmented passes scale the image by up to 1 + this (or its inverse).
        brightness_jitter: ... and their pixel gain by up to 1 +- this.
        seed: the augmentation and the cells kept.
    """

    image_size: int
    passes: int
    cells: int
    scale_jitter: float
    brightness_jitter: float
    seed: int


@dataclass(frozen=True)
class TrainingBuffer:
    """Encoder cells and their targets (see the module).

    Attributes:
        features: [N, C] float16.
        points: [N, 3] float32 world points, NaN rows without depth.
        pixels: [N, 2] float32 original-image pixel (x, y) of each cell.
        views: [N] int64 map image of each cell.
        intrinsics: [M, 4] float32 (fx, fy, cx, cy) per map image.
        rotations: [M, 3, 3] float32 world-to-camera rotations.
        translations: [M, 3] float32 world-to-camera translations.
        centres: [M, 3] float64 camera centres (the map poses' positions).
    """

    features: torch.Tensor
    points: torch.Tensor
    pixels: torch.Tensor
    views: torch.Tensor
    intrinsics: torch.Tensor
    rotations: torch.Tensor
    translations: torch.Tensor
    centres: np.ndarray

    def __len__(self) -> int:
        return len(self.features)


def registered_depth(view: MapImage, scale: DepthScale) -> np.ndarray | None:
    """The view's depth in its image's pixels (metres, NaN where none), judged with the
    map's depth scale (`scale`, as refine=features' depth map is): None for a frame
    whose own median depth is implausible in a plausible map (one note names it); a
    DataError naming the view and why its depth cannot be read (naming the file)."""
    map_view = MapView(
        image=view.image,
        pose=view.pose,
        camera=view.camera,
        depth_path=view.depth_path,
        name=view.name,
        depth_units_per_metre=view.depth_units_per_metre,
        depth_camera=view.depth_camera,
        depth_to_colour=view.depth_to_colour,
    )
    depth, reason = raw_depth(map_view)
    if depth is None:
        raise DataError(f"refine=scene_coordinates (depth): map image {view.name!r}: {reason}")
    return judged_depth(map_view, depth, scale)[0]


def checked_view(view: MapImage) -> None:
    """A DataError naming the map image whose pixels, pose or camera cannot be used."""
    check_rgb_image(view.image, f"map image {view.name!r}")
    if not view.pose.is_finite:
        raise DataError(f"map image {view.name!r}: pose holds NaN or infinity")
    height, width = view.image.shape[:2]
    if view.camera is None or (view.camera.width, view.camera.height) != (width, height):
        size = "none" if view.camera is None else f"{view.camera.width}x{view.camera.height}"
        raise DataError(
            f"map image {view.name!r} is {width}x{height} but its camera is {size}: "
            "refine=scene_coordinates needs each map image's own intrinsics"
        )


def build_buffer(
    views: Sequence[MapImage],
    encoder: Encoder,
    settings: BufferSettings,
    use_depth: bool,
    quiet: bool = True,
) -> TrainingBuffer:
    """Run the encoder over every map image's passes and keep a random share of cells.

    Raises:
        DataError: naming the map image whose pixels, pose or camera are unusable, or
            (use_depth) whose depth file is missing or unreadable, or a depth file when
            the map's depth is implausible in metres (DepthScale), or when no cell of
            any map image has a depth reading.
    """
    for view in views:
        checked_view(view)
    rng = np.random.default_rng(settings.seed)
    # The same share of every pass, so each map image weighs the same in training.
    per_pass = max(1, -(-settings.cells // (len(views) * settings.passes)))
    kept: dict[str, list] = {"features": [], "points": [], "pixels": [], "views": []}
    progress = Progress(len(views), "scene coordinates: encoder passes", quiet=quiet)
    scale = DepthScale(len(views))
    for number, view in enumerate(views):
        depth = registered_depth(view, scale) if use_depth else None
        if use_depth and depth is None:
            progress.advance()  # a close-range frame: no cell of it has a target
            continue
        for repeat in range(settings.passes):
            jitter = (
                PLAIN
                if repeat == 0
                else random_jitter(rng, settings.scale_jitter, settings.brightness_jitter)
            )
            pixels_in, factors = encoder_input(view.image, settings.image_size, jitter)
            with torch.inference_mode():
                maps = encoder(pixels_in)[0]
            channels, rows, columns = maps.shape
            features = maps.reshape(channels, -1).T
            pixels = cell_pixels(rows, columns, factors)
            if depth is None:
                points = np.full((len(pixels), 3), np.nan)
                usable = np.arange(len(pixels))
            else:
                points = lift_keypoints(pixels, depth, view.camera, view.pose)
                usable = np.flatnonzero(np.isfinite(points).all(axis=1))
            chosen = rng.permutation(usable)[:per_pass]
            kept["features"].append(features[torch.from_numpy(chosen)].to(torch.float16))
            kept["points"].append(points[chosen].astype(np.float32))
            kept["pixels"].append(pixels[chosen].astype(np.float32))
            kept["views"].append(np.full(len(chosen), number, dtype=np.int64))
        progress.advance()
    progress.close()
    if use_depth:
        scale.finish()
    if sum(len(v) for v in kept["views"]) == 0:
        raise DataError(
            f"refine=scene_coordinates found no depth reading at any cell of the "
            f"{len(views)} map images (first: {views[0].name!r})"
        )
    return TrainingBuffer(
        features=torch.cat(kept["features"]),
        points=torch.from_numpy(np.concatenate(kept["points"])),
        pixels=torch.from_numpy(np.concatenate(kept["pixels"])),
        views=torch.from_numpy(np.concatenate(kept["views"])),
        **view_geometry(views),
    )


def view_geometry(views: Sequence[MapImage]) -> dict:
    """Per map image: intrinsics, world-to-camera rotation and translation, centre."""
    intrinsics, rotations, translations = [], [], []
    for view in views:
        camera_to_world = quaternion_to_matrix(view.pose.quaternion)
        rotations.append(camera_to_world.T)
        translations.append(-camera_to_world.T @ view.pose.position)
        intrinsics.append([view.camera.fx, view.camera.fy, view.camera.cx, view.camera.cy])
    return {
        "intrinsics": torch.tensor(np.array(intrinsics), dtype=torch.float32),
        "rotations": torch.tensor(np.array(rotations), dtype=torch.float32),
        "translations": torch.tensor(np.array(translations), dtype=torch.float32),
        "centres": np.array([view.pose.position for view in views], dtype=np.float64),
    }
