"""Relative-pose (essential matrix) solvers on synthetic pairs: PoseLib against OpenCV.

Each problem is a keyframe camera at a random spot of a 3 m room looking at a random
point of it, and a query camera 10-50 cm from it, turned by up to 20 degrees (what
retrieved keyframes of a recording look like); the room's random points seen by both
(up to --points, 0.3 m ahead or more) are projected into both images, every pixel gets
Gaussian noise (--noise-px) and a share of the query's pixels (--outliers) is replaced
by uniform random ones, as wrong matches would be (7-Scenes' 640 x 480 camera). All
solvers see the same matches with the same epipolar inlier bound (--max-error px) and
the same rule for success (--min-inliers):

- poselib: relocfw.structure.relative_pose.solve_relative_pose (PoseLib's 5-point
  LO-RANSAC, Sampson error, then a robust refinement over the inliers);
- opencv_ransac: cv2.findEssentialMat (5-point RANSAC, 0.999 confidence) and
  cv2.recoverPose (the cheirality check), no refinement;
- opencv_magsac: the same with cv2.USAC_MAGSAC.

Reported per solver: the rotation error (degrees), the angle between the true and the
found translation direction (degrees: the ray the keyframe family intersects), the
failures and the time. Timing is round robin (the first solver rotating between
problems) with one OpenCV thread. Prints a table, writes JSON.

    .venv/bin/python benchmarks/relative_solvers.py --problems 200
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from common import write_json  # benchmarks/, the script's own folder

from relocfw.core.camera import SEVENSCENES_DEFAULT, PinholeCamera
from relocfw.structure.relative_pose import solve_relative_pose

ROOM_METRES = 3.0
# A solver's answer: (rotation x_q = R x_k + t, unit t), None when it failed.
Answer = tuple[np.ndarray, np.ndarray] | None


def rotation_about(axis: np.ndarray, degrees: float) -> np.ndarray:
    """The rotation by `degrees` about `axis` (Rodrigues)."""
    vector = np.asarray(axis, dtype=np.float64)
    return cv2.Rodrigues(vector / np.linalg.norm(vector) * np.radians(degrees))[0]


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation of an upright camera (world z up) facing `target`."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross([0.0, 0.0, -1.0], forward)
    right /= np.linalg.norm(right)
    return np.column_stack([right, np.cross(forward, right), forward])


def project(camera: PinholeCamera, in_camera: np.ndarray) -> np.ndarray:
    return np.column_stack(
        [
            camera.fx * in_camera[:, 0] / in_camera[:, 2] + camera.cx,
            camera.fy * in_camera[:, 1] / in_camera[:, 2] + camera.cy,
        ]
    )


def make_problem(
    seed: int, camera: PinholeCamera, points: int, noise_px: float, outliers: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(true R, true unit t, [N, 2] keyframe pixels, [N, 2] query pixels)."""
    rng = np.random.default_rng(seed)
    while True:
        centre = rng.uniform(0.5, ROOM_METRES - 0.5, 3)
        target = rng.uniform(0.0, ROOM_METRES, 3)
        if np.linalg.norm(target - centre) < 1.0:
            continue
        keyframe = look_at(centre, target)  # camera-to-world
        step = rng.normal(size=3)
        query_centre = centre + step / np.linalg.norm(step) * rng.uniform(0.1, 0.5)
        turn = rotation_about(rng.normal(size=3), rng.uniform(0.0, 20.0))
        query = keyframe @ turn
        world = rng.uniform(0.0, ROOM_METRES, (20 * points, 3))
        in_keyframe = (world - centre) @ keyframe
        in_query = (world - query_centre) @ query
        pixels_k, pixels_q = project(camera, in_keyframe), project(camera, in_query)
        inside = (
            (in_keyframe[:, 2] > 0.3)
            & (in_query[:, 2] > 0.3)
            & np.all((pixels_k >= 0) & (pixels_k <= [camera.width - 1, camera.height - 1]), 1)
            & np.all((pixels_q >= 0) & (pixels_q <= [camera.width - 1, camera.height - 1]), 1)
        )
        if inside.sum() >= points:
            break
    chosen = np.flatnonzero(inside)[:points]
    pixels_k = pixels_k[chosen] + rng.normal(0.0, noise_px, (points, 2))
    pixels_q = pixels_q[chosen] + rng.normal(0.0, noise_px, (points, 2))
    wrong = rng.random(points) < outliers
    pixels_q[wrong] = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], (wrong.sum(), 2))
    # x_q = query^T (X - c_q) = query^T keyframe x_k + query^T (c_k - c_q).
    rotation = query.T @ keyframe
    translation = query.T @ (centre - query_centre)
    return rotation, translation / np.linalg.norm(translation), pixels_k, pixels_q


def poselib_solver(max_error: float, min_inliers: int) -> Callable:
    def solve(pixels_k: np.ndarray, pixels_q: np.ndarray, camera: PinholeCamera) -> Answer:
        found = solve_relative_pose(pixels_k, pixels_q, camera, camera, max_error, min_inliers)
        return (found.rotation, found.direction) if found.success else None

    return solve


def opencv_solver(method: int, max_error: float, min_inliers: int) -> Callable:
    def solve(pixels_k: np.ndarray, pixels_q: np.ndarray, camera: PinholeCamera) -> Answer:
        matrix = np.array(
            [[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]], dtype=np.float64
        )
        essential, mask = cv2.findEssentialMat(
            pixels_k, pixels_q, matrix, method=method, prob=0.999, threshold=max_error
        )
        if essential is None or essential.shape != (3, 3) or mask is None:
            return None  # several solutions stacked, or none: no single pose
        inliers, rotation, translation, _ = cv2.recoverPose(
            essential, pixels_k, pixels_q, matrix, mask=mask.copy()
        )
        if inliers < min_inliers:
            return None
        return rotation, translation.ravel() / np.linalg.norm(translation)

    return solve


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0))))


def rotation_error_deg(estimate: np.ndarray, truth: np.ndarray) -> float:
    cosine = (np.trace(estimate.T @ truth) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def summary(errors: list[tuple[float, float] | None], seconds: list[float]) -> dict:
    solved = np.array([e for e in errors if e is not None]).reshape(-1, 2)

    def stat(column: int, percentile: float) -> float | None:
        return float(np.percentile(solved[:, column], percentile)) if len(solved) else None

    return {
        "solved": len(solved),
        "failed": len(errors) - len(solved),
        "median_rotation_deg": stat(0, 50),
        "p90_rotation_deg": stat(0, 90),
        "median_direction_deg": stat(1, 50),
        "p90_direction_deg": stat(1, 90),
        "median_ms": 1000 * float(np.median(seconds)),
        "mean_ms": 1000 * float(np.mean(seconds)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=int, default=200)
    parser.add_argument("--points", type=int, default=200, help="matches per problem")
    parser.add_argument("--noise-px", type=float, default=1.0)
    parser.add_argument("--outliers", type=float, default=0.4, help="share of wrong matches")
    parser.add_argument("--max-error", type=float, default=2.0, help="epipolar bound, pixels")
    parser.add_argument("--min-inliers", type=int, default=15)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/relative_solvers.json")
    )
    args = parser.parse_args()
    if args.problems < 1:
        parser.error("--problems must be at least 1")

    import poselib

    cv2.setNumThreads(1)
    camera = SEVENSCENES_DEFAULT
    solvers = {
        "poselib": poselib_solver(args.max_error, args.min_inliers),
        "opencv_ransac": opencv_solver(cv2.RANSAC, args.max_error, args.min_inliers),
        "opencv_magsac": opencv_solver(cv2.USAC_MAGSAC, args.max_error, args.min_inliers),
    }
    problems = [
        make_problem(args.seed + i, camera, args.points, args.noise_px, args.outliers)
        for i in range(args.problems)
    ]
    for solve in solvers.values():  # warm-up: first-call costs are not a solve's
        solve(problems[0][2], problems[0][3], camera)

    names = list(solvers)
    errors: dict[str, list] = {name: [] for name in names}
    seconds: dict[str, list] = {name: [] for name in names}
    for index, (rotation, direction, pixels_k, pixels_q) in enumerate(problems):
        shift = index % len(names)
        for name in names[shift:] + names[:shift]:
            start = time.perf_counter()
            found = solvers[name](pixels_k, pixels_q, camera)
            seconds[name].append(time.perf_counter() - start)
            errors[name].append(
                None
                if found is None
                else (rotation_error_deg(found[0], rotation), angle_deg(found[1], direction))
            )

    rows = {name: summary(errors[name], seconds[name]) for name in names}
    print(
        f"{args.problems} pairs, {args.points} matches, {args.noise_px} px noise, "
        f"{args.outliers:.0%} outliers, epipolar bound {args.max_error} px"
    )
    print(f"{'solver':<14} {'solved':>8} {'rot deg':>8} {'dir deg':>8} {'p90 dir':>8} {'ms':>7}")
    for name, row in rows.items():
        print(
            f"{name:<14} {row['solved']:>4}/{args.problems:<3}"
            f" {row['median_rotation_deg'] or float('nan'):>8.3f}"
            f" {row['median_direction_deg'] or float('nan'):>8.3f}"
            f" {row['p90_direction_deg'] or float('nan'):>8.3f}"
            f" {row['median_ms']:>7.2f}"
        )
    report = {
        "problems": args.problems,
        "points": args.points,
        "noise_px": args.noise_px,
        "outliers": args.outliers,
        "max_error_px": args.max_error,
        "min_inliers": args.min_inliers,
        "seed": args.seed,
        "camera": [camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height],
        "versions": {"poselib": poselib.__version__, "opencv": cv2.__version__},
        "machine": platform.processor() or platform.machine(),
        "timing": "round robin, the first solver rotating per problem; one thread each",
        "solvers": rows,
    }
    write_json(report, args.out)


if __name__ == "__main__":
    main()
