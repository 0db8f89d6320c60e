"""A camera's pose from 2-D/3-D correspondences: P3P in LO-RANSAC, then refinement.

The solver is PoseLib's (Larsson and contributors; `poselib.estimate_absolute_pose`):
minimal P3P samples in locally optimised RANSAC, then a robust (Cauchy) non-linear
refinement of the reprojection error over the inliers. It is an optional dependency
(`pip install "relocfw[structure]"`), imported only when a pose is solved.
benchmarks/structure_solvers.py compares it with pycolmap's solver.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relocfw.core.arrays import point_rows
from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import conjugate, quaternion_to_matrix
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.values import Pose

MINIMUM_CORRESPONDENCES = 4  # P3P's three plus one to choose among its solutions
RANSAC_SEED = 0  # fixed: the same correspondences give the same pose on every run
# PoseLib's own least number of RANSAC rounds. Past it, rounds stop once a pose with
# the inliers found so far would have been drawn with probability 0.9999; with many
# inliers that takes far fewer rounds, so the least number is most of the solve's time
# (about 5 ms of 6 for 300 clean correspondences).
POSELIB_MIN_ITERATIONS = 1000
# PoseLib's own most rounds: a least number above it (a typo, or a crafted model file)
# would make every query run that long.
POSELIB_MAX_ITERATIONS = 100_000


@dataclass(frozen=True)
class AbsolutePose:
    """The result of one absolute-pose solve.

    Attributes:
        pose: camera-to-world Pose (metres, quaternion w first), None when the solve
            failed.
        inliers: correspondences within the error bound of the pose found (0 when
            none was found).
        success: True when a pose was found with at least the required inliers.
    """

    pose: Pose | None
    inliers: int
    success: bool


def failed(inliers: int = 0) -> AbsolutePose:
    """The result of a solve that found no usable pose."""
    return AbsolutePose(pose=None, inliers=inliers, success=False)


def checked_correspondences(
    points_2d: np.ndarray, points_3d: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """[N, 2] and [N, 3] float64 arrays of finite numbers, or a DataError naming the
    argument at fault."""
    image = point_rows(points_2d, "points_2d", 2)
    world = point_rows(points_3d, "points_3d", 3)
    if len(image) != len(world):
        raise DataError(
            f"points_2d has {len(image)} rows, points_3d {len(world)}; row i of each must "
            "be one correspondence"
        )
    return image, world


def pose_of_world_to_camera(quaternion: np.ndarray, translation: np.ndarray) -> Pose:
    """The camera-to-world Pose of a world-to-camera rotation (w first) and
    translation: camera = R world + t, so the centre is -R^T t and the rotation R^T."""
    rotation = quaternion_to_matrix(quaternion)
    centre = -rotation.T @ np.asarray(translation, dtype=np.float64)
    q = np.asarray(quaternion, dtype=np.float64)
    return Pose(centre, conjugate(q / np.linalg.norm(q)))


def solve_absolute_pose(
    points_2d: np.ndarray,
    points_3d: np.ndarray,
    camera: PinholeCamera,
    max_error_px: float = 8.0,
    min_inliers: int = 12,
    min_iterations: int = POSELIB_MIN_ITERATIONS,
) -> AbsolutePose:
    """The camera-to-world pose that projects `points_3d` onto `points_2d`.

    Args:
        points_2d: [N, 2] pixel (x, y) of keypoints in the image `camera` describes.
        points_3d: [N, 3] world points in metres; row i is seen at row i of points_2d.
            Any share may be outliers (wrong matches); RANSAC sorts them out.
        camera: intrinsics of the image (undistorted pinhole).
        max_error_px: the reprojection error in pixels under which a correspondence is
            an inlier (> 0).
        min_inliers: the fewest inliers a pose needs to count as found (>= 4).
        min_iterations: the fewest RANSAC rounds (>= 1); more rounds stop by
            PoseLib's confidence rule (see POSELIB_MIN_ITERATIONS).

    Returns:
        AbsolutePose. A solve that fails (fewer than 4 correspondences, no pose, fewer
        than `min_inliers` inliers) returns success False and pose None; it never
        raises, since failing is an expected outcome for a hard query.

    Raises:
        DataError: naming the argument when the arrays have the wrong shapes, differ
            in length or hold NaN or infinity.
        ConfigError: naming `max_error_px` or `min_inliers` when out of range, or when
            poselib is not installed.
    """
    image, world = checked_correspondences(points_2d, points_3d)
    max_error = positive_number("max_error_px", max_error_px)
    min_inliers = integer_at_least("min_inliers", min_inliers, MINIMUM_CORRESPONDENCES)
    min_iterations = integer_at_least("min_iterations", min_iterations, 1)
    if min_iterations > POSELIB_MAX_ITERATIONS:
        raise ConfigError(
            f"min_iterations must be at most {POSELIB_MAX_ITERATIONS} (PoseLib's most "
            f"rounds), got {min_iterations}"
        )
    try:
        import poselib
    except ImportError:
        raise ConfigError(
            'local-feature refinement needs poselib: pip install "relocfw[structure]"'
        ) from None
    if len(image) < MINIMUM_CORRESPONDENCES:
        return failed()

    camera_model = {
        "model": "PINHOLE",
        "width": camera.width,
        "height": camera.height,
        "params": [camera.fx, camera.fy, camera.cx, camera.cy],
    }
    ransac = {
        "max_reproj_error": max_error,
        "seed": RANSAC_SEED,
        "min_iterations": min_iterations,
        "max_iterations": POSELIB_MAX_ITERATIONS,
    }
    world_to_camera, info = poselib.estimate_absolute_pose(image, world, camera_model, ransac, {})
    inliers = int(info.get("num_inliers", 0))
    q = np.asarray(world_to_camera.q, dtype=np.float64)
    t = np.asarray(world_to_camera.t, dtype=np.float64)
    # PoseLib returns the identity with no inliers when RANSAC found nothing.
    if inliers < min_inliers or not (np.isfinite(q).all() and np.isfinite(t).all()):
        return failed(inliers)
    return AbsolutePose(pose=pose_of_world_to_camera(q, t), inliers=inliers, success=True)
