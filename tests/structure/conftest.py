"""The synthetic scene the structure-map and query tests share, rendered once."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from relocfw.core.camera import SEVENSCENES_DEFAULT, PinholeCamera
from relocfw.core.values import Pose
from relocfw.data.sevenscenes import REGISTERED_MARKER
from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.map_view import MapView
from relocfw.structure.structure_map import StructureMap
from relocfw.structure.triangulated_structure import build_by_triangulation
from tests.structure.textured_world import (
    Quad,
    depth_map,
    looking_at,
    make_world,
    render,
    write_depth_png,
)

CAMERA = SEVENSCENES_DEFAULT  # 640 x 480, fx = fy = 585


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """Three map views of a textured room corner (with depth PNGs) and a query.

    Attributes:
        world: the quads (tests.structure.textured_world).
        camera: every image's camera.
        views: the map views: two 0.6 m apart looking at the back wall, a third
            0.2 m above them; each with its depth PNG.
        depths: their [H, W] depth maps in metres.
        query_pose: the query's camera-to-world pose, between the first two views.
        query_image: the query's [H, W, 3] uint8 image.
    """

    world: list[Quad]
    camera: PinholeCamera
    views: tuple[MapView, ...]
    depths: tuple[np.ndarray, ...]
    query_pose: Pose
    query_image: np.ndarray


@pytest.fixture(scope="session")
def synthetic_scene(tmp_path_factory: pytest.TempPathFactory) -> SyntheticScene:
    folder: Path = tmp_path_factory.mktemp("synthetic_scene")
    world = make_world(seed=0)
    poses = [
        looking_at([-0.3, 0.0, 0.0], [0.0, 0.0, 3.0]),
        looking_at([0.3, 0.05, 0.0], [0.0, 0.0, 3.0]),
        looking_at([0.0, -0.2, -0.1], [0.1, 0.0, 3.0]),
    ]
    views, depths = [], []
    for number, pose in enumerate(poses):
        depth = depth_map(world, pose, CAMERA)
        path = write_depth_png(depth, folder / f"view-{number}.depth.png")
        views.append(MapView(render(world, pose, CAMERA), pose, CAMERA, path, f"view-{number}"))
        depths.append(depth)
    query_pose = looking_at([0.05, 0.1, 0.2], [-0.1, 0.0, 3.0])
    return SyntheticScene(
        world=world,
        camera=CAMERA,
        views=tuple(views),
        depths=tuple(depths),
        query_pose=query_pose,
        query_image=render(world, query_pose, CAMERA),
    )


@pytest.fixture(scope="session")
def depth_structure(synthetic_scene: SyntheticScene) -> StructureMap:
    """The depth-built map of the first two views (the query lies between them)."""
    return build_from_depth(synthetic_scene.views[:2], max_features=1024, quiet=True)


@pytest.fixture(scope="session")
def triangulated_structure(synthetic_scene: SyntheticScene) -> StructureMap:
    """The map of all three views by triangulation, each with the other two."""
    return build_by_triangulation(synthetic_scene.views, max_features=1024, partners=2, quiet=True)


@pytest.fixture
def raw_kinect_scene(tiny_scene: Path, tmp_path: Path) -> Path:
    """The tiny synthetic scene as a 7-Scenes copy with raw (unregistered) depth."""
    copy = tmp_path / "room"
    shutil.copytree(tiny_scene, copy)
    (copy / REGISTERED_MARKER).unlink()
    return copy
