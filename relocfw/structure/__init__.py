"""Structure-based relocalization, the library layer: local features, a 3-D map, PnP.

One job per module: `features` (SIFT keypoints, RootSIFT descriptors), `matching`
(mutual nearest neighbours with Lowe's ratio test, one matrix product), `lifting`
(keypoints to world points with a depth map), `triangulation` (world points from two
posed views), `covisibility` and `tracks` (an RGB-only map's partners and multi-view
tracks), `map_quality` (how many keypoints have a point, how far from depth),
`absolute_pose` (P3P LO-RANSAC and refinement through PoseLib);
`map_view` (a map image as the builders take it), `structure_map` (the map's
features and 3-D points, one npz file); one builder per 3-D source:
`depth_structure`, `triangulated_structure` (choosing `track_structure` or
`two_view_structure`) and `colmap_structure` (a COLMAP model's own 3-D points), with
`view_features` (map views checked, and read once with their features);
`structure_cache` (a map's content key, one cached file per key),
`query_solver` (one query's pose against the map, keyframe choice). The pinhole
camera is `relocfw.core.camera` (relocfw.data reads it from files and may import
only the core); it is re-exported here.

This part may import only relocfw.core and relocfw.data (tests/core/test_layout.py).
"""

from relocfw.core.camera import SEVENSCENES_DEFAULT, PinholeCamera
from relocfw.structure.absolute_pose import AbsolutePose, solve_absolute_pose
from relocfw.structure.colmap_structure import build_from_colmap_points
from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.features import LocalFeatures, extract_rootsift
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.map_view import MapView
from relocfw.structure.matching import match_against_views, mutual_nearest_neighbours
from relocfw.structure.query_solver import (
    MapViewpoints,
    StructureAnswer,
    keyframes_by_pose,
    localize_against,
)
from relocfw.structure.structure_cache import cached_structure_map, structure_key
from relocfw.structure.structure_map import SkippedView, StructureMap
from relocfw.structure.track_structure import build_by_track_triangulation
from relocfw.structure.triangulated_structure import build_by_triangulation
from relocfw.structure.triangulation import triangulate
from relocfw.structure.two_view_structure import (
    build_by_two_view_triangulation,
    triangulation_partners,
)

__all__ = [
    "SEVENSCENES_DEFAULT",
    "AbsolutePose",
    "LocalFeatures",
    "MapView",
    "MapViewpoints",
    "PinholeCamera",
    "SkippedView",
    "StructureAnswer",
    "StructureMap",
    "build_by_track_triangulation",
    "build_by_triangulation",
    "build_from_colmap_points",
    "build_by_two_view_triangulation",
    "build_from_depth",
    "cached_structure_map",
    "extract_rootsift",
    "keyframes_by_pose",
    "lift_keypoints",
    "localize_against",
    "match_against_views",
    "mutual_nearest_neighbours",
    "solve_absolute_pose",
    "structure_key",
    "triangulate",
    "triangulation_partners",
]
