"""A tiny rendered room for the scene-coordinate tests: map images with depth PNGs.

Small images (160 x 120) and an encoder image of 120 px keep a fit to seconds on one
core; the head learns the room from seven views two rows apart.
"""

from __future__ import annotations

from pathlib import Path

from relocfw.core.camera import SEVENSCENES_DEFAULT
from relocfw.core.refinement import MapImage
from tests.structure.textured_world import (
    depth_map,
    looking_at,
    make_world,
    render,
    write_depth_png,
)

CAMERA = SEVENSCENES_DEFAULT.scaled_to(160, 120)
MAP_POSITIONS = [[-0.45, 0.0, 0.0], [-0.15, 0.0, 0.0], [0.15, 0.0, 0.0], [0.45, 0.0, 0.0]]
MAP_POSITIONS += [[x, -0.2, -0.1] for x in (-0.3, 0.0, 0.3)]
# Small and quick: a fit of a few seconds (the defaults are for real scenes).
QUICK = {
    "image_size": 120,
    "passes": 2,
    "buffer_size": 20000,
    "head_width": 256,  # the tests' figures were measured at 256 (the default is auto)
    "max_error_px": 10.0,  # ... and at 10 px (the default is auto)
    "steps": 300,
    "batch_size": 512,
    "lr": 3e-3,
    "min_inliers": 12,
    "quiet": True,
}


def room_views(folder: Path) -> tuple[list, list[MapImage]]:
    """The room's quads and its map images, each with a depth PNG in `folder`."""
    world = make_world(seed=0)
    views = []
    for number, position in enumerate(MAP_POSITIONS):
        pose = looking_at(position, [position[0] * 0.5, 0.0, 3.0])
        depth = write_depth_png(depth_map(world, pose, CAMERA), folder / f"m{number}.depth.png")
        image = render(world, pose, CAMERA, supersample=1)
        views.append(MapImage(f"seq-01/frame-{number:06d}", image, pose, CAMERA, depth))
    return world, views
