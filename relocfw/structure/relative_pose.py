"""A query's pose from its relative poses to keyframes: the essential matrix, then rays.

The keyframe-based family (select the most similar keyframes, estimate the relative
pose, transfer it to the world frame) needs no 3-D point and no depth:

1. Per keyframe, the relative pose of the query from their 2-D/2-D matches: the
   essential matrix by the 5-point solver in LO-RANSAC with the Sampson error as the
   inlier test, refined over the inliers (`solve_relative_pose`). It gives the
   rotation and the DIRECTION of the translation only: its length is unknowable from
   two images.
2. A pair whose inliers barely move between the two views (median parallax under a
   few tenths of a degree: the query stands where the keyframe stood, or the pair is
   pure rotation) has a rotation but no usable direction; such pairs are not used.
3. Each usable keyframe gives a ray in the world: from its camera centre along the
   direction towards the query's centre. The query's centre is the point nearest to
   the rays in least squares (`intersect_rays`), found by consensus over pairs of
   rays so one wrong keyframe does not pull it (`locate_by_rays`): the pair whose
   intersection most inliers' worth of rays agree with wins, and its agreeing rays are
   intersected together. Rays must cross at an angle: near-parallel rays (all
   keyframes on one line with the query) fix no position along them.
4. The rotation is the inlier-weighted mean of the rotations the agreeing keyframes
   give.

Solver: PoseLib's `estimate_relative_pose` (the 5-point solver in LO-RANSAC, then a
robust refinement of the Sampson error over the inliers), not OpenCV's
`findEssentialMat` + `recoverPose`. benchmarks/relative_solvers.py, 200 synthetic pairs
(640 x 480, 10-50 cm apart, 1 px noise, 40% outliers, 2 px bound; benchmarks/results/
relative_solvers.json), median rotation / direction error (90th percentile of the
direction) and time per pair, one thread:

- PoseLib: 0.20 / 0.57 deg (1.65 deg), 6.0 ms;
- OpenCV USAC_MAGSAC: 0.27 / 0.76 deg (2.83 deg), 5.4 ms;
- OpenCV RANSAC: 0.76 / 2.41 deg (6.60 deg), 39.7 ms.

The direction is what the rays are intersected with, so its tail matters most:
PoseLib's is 40% tighter at about the same time as MAGSAC. It is also the solver of
relocfw's absolute pose (relocfw.structure.absolute_pose): no new dependency.

Conventions as relocfw.core.camera: camera x right, y down, z forward; poses are
camera-to-world. A relative pose maps keyframe-camera coordinates to query-camera
ones: x_query = R x_keyframe + t (PoseLib's), with |t| = 1.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from relocfw.core.arrays import point_rows
from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import matrix_to_quaternion, mean_quaternion, quaternion_to_matrix
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.values import Pose

MINIMUM_CORRESPONDENCES = 5  # the 5-point solver's sample
RANSAC_SEED = 0  # fixed: the same matches give the same pose on every run
# PoseLib draws at least 1000 samples by default; its adaptive stopping rule ends far
# sooner at the outlier shares of real matches. benchmarks/relative_solvers.py: 100
# gave the same errors (median and 90th percentile) in half the time.
MIN_ITERATIONS = 100
# Below this, the smallest eigenvalue of the normal matrix of the rays (a sum of
# projections, each with eigenvalues 0 and 1 x its weight) says the rays are parallel:
# the least-squares point is then a line, not a point.
SINGULAR_SHARE = 1e-9


@dataclass(frozen=True)
class RelativePose:
    """The pose of a query relative to one keyframe.

    Attributes:
        rotation: [3, 3] keyframe-camera to query-camera rotation (x_q = R x_k + t).
        direction: [3] unit translation t, in the query camera's frame.
        inliers: matches within the epipolar bound of the pose found (0: none found).
        parallax_deg: the median angle between the inliers' two viewing rays (in one
            frame): how much the pair sees its points move; near 0 the direction is
            noise (no baseline, pure rotation).
        success: True when a pose with at least the required inliers was found.
    """

    rotation: np.ndarray = field(repr=False)
    direction: np.ndarray
    inliers: int
    parallax_deg: float
    success: bool


def failed_relative(inliers: int = 0) -> RelativePose:
    """The result of a relative solve that found no usable pose."""
    return RelativePose(np.full((3, 3), np.nan), np.full(3, np.nan), inliers, 0.0, False)


def camera_dict(camera: PinholeCamera) -> dict:
    """The camera as PoseLib reads it."""
    return {
        "model": "PINHOLE",
        "width": camera.width,
        "height": camera.height,
        "params": [camera.fx, camera.fy, camera.cx, camera.cy],
    }


def bearings(pixels: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """[N, 3] unit viewing directions of pixels, in the camera's frame."""
    rays = np.column_stack(
        [
            (pixels[:, 0] - camera.cx) / camera.fx,
            (pixels[:, 1] - camera.cy) / camera.fy,
            np.ones(len(pixels)),
        ]
    )
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def median_parallax_deg(
    keyframe_pixels: np.ndarray,
    query_pixels: np.ndarray,
    keyframe_camera: PinholeCamera,
    query_camera: PinholeCamera,
    rotation: np.ndarray,
) -> float:
    """The median angle, in degrees, between each match's keyframe ray and its query
    ray turned into the keyframe's frame: zero for every point when the two centres
    coincide, whatever the rotation (no depth and no direction can be told)."""
    if len(keyframe_pixels) == 0:
        return 0.0
    keyframe_rays = bearings(keyframe_pixels, keyframe_camera)
    query_rays = bearings(query_pixels, query_camera) @ rotation  # R^T r, row-wise
    cosines = np.clip(np.sum(keyframe_rays * query_rays, axis=1), -1.0, 1.0)
    return float(np.degrees(np.median(np.arccos(cosines))))


def solve_relative_pose(
    keyframe_pixels: np.ndarray,
    query_pixels: np.ndarray,
    keyframe_camera: PinholeCamera,
    query_camera: PinholeCamera,
    max_error_px: float = 2.0,
    min_inliers: int = 15,
) -> RelativePose:
    """The query's pose relative to a keyframe from their matched pixels.

    Args:
        keyframe_pixels: [N, 2] pixel (x, y) in the keyframe.
        query_pixels: [N, 2] pixel (x, y) in the query; row i matches row i.
        keyframe_camera: the keyframe's intrinsics.
        query_camera: the query's intrinsics.
        max_error_px: the Sampson (first-order epipolar) error under which a match is
            an inlier, in pixels (> 0).
        min_inliers: the fewest inliers a pose needs (>= 5).

    Returns:
        RelativePose. Fewer than 5 matches, no pose or too few inliers give success
        False; it never raises for that (a hard query is an expected outcome).

    Raises:
        DataError: naming the argument when the arrays have the wrong shapes, differ
            in length or hold NaN.
        ConfigError: naming `max_error_px` or `min_inliers` when out of range, or when
            poselib is not installed.
    """
    first = point_rows(keyframe_pixels, "keyframe_pixels", 2)
    second = point_rows(query_pixels, "query_pixels", 2)
    if len(first) != len(second):
        raise DataError(
            f"keyframe_pixels has {len(first)} rows, query_pixels {len(second)}; row i of "
            "each must be one match"
        )
    bound = positive_number("max_error_px", max_error_px)
    min_inliers = integer_at_least("min_inliers", min_inliers, MINIMUM_CORRESPONDENCES)
    try:
        import poselib
    except ImportError:
        raise ConfigError(
            'relative-pose refinement needs poselib: pip install "relocfw[structure]"'
        ) from None
    if len(first) < MINIMUM_CORRESPONDENCES:
        return failed_relative()
    ransac = {"max_epipolar_error": bound, "seed": RANSAC_SEED, "min_iterations": MIN_ITERATIONS}
    pose, info = poselib.estimate_relative_pose(
        first, second, camera_dict(keyframe_camera), camera_dict(query_camera), ransac, {}
    )
    inliers = int(info.get("num_inliers", 0))
    rotation = np.asarray(pose.R, dtype=np.float64)
    direction = np.asarray(pose.t, dtype=np.float64)
    length = float(np.linalg.norm(direction))
    usable = np.isfinite(rotation).all() and np.isfinite(direction).all() and length > 0
    if inliers < min_inliers or not usable:
        return failed_relative(inliers)
    mask = np.asarray(info.get("inliers", np.ones(len(first), bool)), dtype=bool)
    parallax = median_parallax_deg(
        first[mask], second[mask], keyframe_camera, query_camera, rotation
    )
    return RelativePose(rotation, direction / length, inliers, parallax, True)


@dataclass(frozen=True)
class QueryRay:
    """What one keyframe says of the query, in the world.

    Attributes:
        origin: [3] the keyframe's camera centre.
        direction: [3] unit world direction from it towards the query's centre.
        rotation: [3, 3] the query's camera-to-world rotation the keyframe gives.
        weight: the pair's inliers.
    """

    origin: np.ndarray
    direction: np.ndarray
    rotation: np.ndarray = field(repr=False)
    weight: float


def query_ray(keyframe_pose: Pose, relative: RelativePose) -> QueryRay:
    """The world ray and rotation of the query one keyframe's relative pose gives.

    With the keyframe's camera-to-world rotation R_k and centre c_k, and x_q = R x_k
    + t, the query's camera-to-world rotation is R_k R^T and its centre c_k - s R_k
    R^T t for some s > 0 (PoseLib chooses the sign of t that puts the inliers in
    front of both cameras).
    """
    keyframe_rotation = quaternion_to_matrix(keyframe_pose.quaternion)
    rotation = keyframe_rotation @ relative.rotation.T
    direction = -rotation @ relative.direction
    return QueryRay(
        origin=np.asarray(keyframe_pose.position, dtype=np.float64),
        direction=direction / np.linalg.norm(direction),
        rotation=rotation,
        weight=float(relative.inliers),
    )


def intersect_rays(
    origins: np.ndarray, directions: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray | None:
    """The point nearest to lines in weighted least squares, None when they are
    (near) parallel.

    Minimises sum_i w_i |(I - d_i d_i^T)(x - o_i)|^2: the normal equations are
    sum_i w_i P_i x = sum_i w_i P_i o_i with P_i the projection off line i.

    Args:
        origins: [N, 3] a point of each line.
        directions: [N, 3] unit directions.
        weights: [N] positive weights (None: all 1).

    Returns:
        [3] the point, or None with fewer than two lines or lines that do not fix a
        point (the normal matrix is singular).
    """
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if len(origins) < 2 or len(directions) != len(origins):
        return None
    weights = np.ones(len(origins)) if weights is None else np.asarray(weights, np.float64)
    projections = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]
    normal = np.einsum("n,nij->ij", weights, projections)
    right = np.einsum("n,nij,nj->i", weights, projections, origins)
    eigenvalues = np.linalg.eigvalsh(normal)
    if not np.isfinite(eigenvalues).all() or eigenvalues[0] <= SINGULAR_SHARE * weights.sum():
        return None
    return np.linalg.solve(normal, right)


def ray_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between two unit directions, in degrees."""
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def angular_errors_deg(rays: Sequence[QueryRay], point: np.ndarray) -> np.ndarray:
    """[N] per ray, the angle between its direction and the direction from its origin
    to `point` (180 for a point behind it, and for a point at its origin: a keyframe
    cannot say the query stands where it stands, which would need no baseline)."""
    errors = []
    for ray in rays:
        towards = point - ray.origin
        length = float(np.linalg.norm(towards))
        errors.append(180.0 if length == 0.0 else ray_angle_deg(ray.direction, towards / length))
    return np.array(errors)


def widest_angle_deg(origins: np.ndarray, point: np.ndarray) -> float:
    """The largest angle at `point` between the directions to two of `origins`: the
    triangulation angle of the query's centre. Small when the keyframes stand close
    together for their distance to the query (a short baseline), whatever the scale."""
    towards = np.asarray(origins, dtype=np.float64) - point
    lengths = np.linalg.norm(towards, axis=1)
    if (lengths == 0.0).any():
        return 0.0
    units = towards / lengths[:, None]
    cosines = np.clip(units @ units.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


@dataclass(frozen=True)
class RayPosition:
    """Where the query's rays meet, and which of them agree.

    Attributes:
        position: [3] the query's centre, None when the rays fix none.
        used: indices of the rays the position rests on (agreeing ones).
        reason: why there is no position ("" when there is one).
    """

    position: np.ndarray | None
    used: tuple[int, ...]
    reason: str = ""


def locate_by_rays(
    rays: Sequence[QueryRay],
    min_rays: int = 2,
    min_angle_deg: float = 3.0,
    max_error_deg: float = 5.0,
) -> RayPosition:
    """The query's centre from keyframe rays, by consensus over pairs of rays.

    Every pair crossing at `min_angle_deg` or more is intersected (the angle between
    the rays, and the angle their two keyframes subtend at the crossing: keyframes
    close together for their distance to it fix no distance, whatever their rays'
    directions); a ray agrees with the point when it points at it within
    `max_error_deg`. The pair whose point the
    most inliers' worth of rays agree with wins (ties: the earlier pair), and all its
    agreeing rays are intersected, weighted by their inliers. A handful of keyframes
    give a few dozen pairs: checking them all costs microseconds, and no random
    sample can miss the right one.

    Args:
        rays: one per keyframe with a usable relative pose.
        min_rays: the fewest agreeing rays a position needs (>= 2: one ray fixes a
            line, not a point).
        min_angle_deg: the least angle between two rays, and between the directions
            from their crossing to their keyframes, for the crossing to count:
            near-parallel rays place the point anywhere along them.
        max_error_deg: how far a ray may point from the position and still agree.

    Returns:
        RayPosition; without a position, `reason` says why (too few rays, rays that
        do not cross at an angle, too few agreeing), never an exception.
    """
    min_rays = integer_at_least("min_rays", min_rays, 2)
    if len(rays) < min_rays:
        return RayPosition(None, (), f"{len(rays)} usable keyframes, fewer than {min_rays}")
    weights = np.array([ray.weight for ray in rays])
    best: tuple[float, tuple[int, ...]] = (-1.0, ())
    crossing = False
    for first, second in itertools.combinations(range(len(rays)), 2):
        a, b = rays[first], rays[second]
        if ray_angle_deg(a.direction, b.direction) < min_angle_deg:
            continue
        point = intersect_rays(np.stack([a.origin, b.origin]), np.stack([a.direction, b.direction]))
        if point is None or widest_angle_deg(np.stack([a.origin, b.origin]), point) < (
            min_angle_deg
        ):
            continue
        crossing = True
        agreeing = np.flatnonzero(angular_errors_deg(rays, point) <= max_error_deg)
        if first not in agreeing or second not in agreeing:
            continue  # the pair's own rays miss their crossing: they pass each other
        support = float(weights[agreeing].sum())
        if support > best[0]:
            best = (support, tuple(int(i) for i in agreeing))
    if not crossing:
        return RayPosition(None, (), f"no two rays cross at {min_angle_deg} degrees or more")
    used = best[1]
    if len(used) < min_rays:
        return RayPosition(None, used, f"fewer than {min_rays} rays agree on a position")
    chosen = [rays[i] for i in used]
    position = intersect_rays(
        np.stack([r.origin for r in chosen]),
        np.stack([r.direction for r in chosen]),
        weights[list(used)],
    )
    if position is None or (angular_errors_deg(chosen, position) > max_error_deg).any():
        return RayPosition(None, used, "the agreeing rays do not meet at one point")
    if widest_angle_deg(np.stack([r.origin for r in chosen]), position) < min_angle_deg:
        return RayPosition(None, used, "the keyframes are too close together to place it")
    return RayPosition(position, used)


def mean_rotation(rays: Sequence[QueryRay]) -> np.ndarray:
    """[4] the inlier-weighted mean (Markley's) of the rays' query rotations, as a
    unit quaternion (w first)."""
    quaternions = np.stack([matrix_to_quaternion(ray.rotation) for ray in rays])
    return mean_quaternion(quaternions, np.array([ray.weight for ray in rays]))
