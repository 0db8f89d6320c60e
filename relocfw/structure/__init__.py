"""Structure-based relocalization, the library layer: local features, a 3-D map, PnP.

One job per module: `features` (SIFT keypoints, RootSIFT descriptors), `matching`
(mutual nearest neighbours with Lowe's ratio test, one matrix product), `lifting`
(keypoints to world points with a depth map), `triangulation` (world points from two
posed views), `absolute_pose` (P3P LO-RANSAC and refinement through PoseLib). The
pinhole camera is `relocfw.core.camera` (relocfw.data reads it from files and may
import only the core); it is re-exported here.

This part may import only relocfw.core (tests/core/test_layout.py).
"""

from relocfw.core.camera import SEVENSCENES_DEFAULT, PinholeCamera
from relocfw.structure.absolute_pose import AbsolutePose, solve_absolute_pose
from relocfw.structure.features import LocalFeatures, extract_rootsift
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.matching import match_against_views, mutual_nearest_neighbours
from relocfw.structure.triangulation import triangulate

__all__ = [
    "SEVENSCENES_DEFAULT",
    "AbsolutePose",
    "LocalFeatures",
    "PinholeCamera",
    "extract_rootsift",
    "lift_keypoints",
    "match_against_views",
    "mutual_nearest_neighbours",
    "solve_absolute_pose",
    "triangulate",
]
