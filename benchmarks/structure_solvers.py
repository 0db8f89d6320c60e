"""Absolute-pose solvers on synthetic correspondences: PoseLib against pycolmap.

Each problem is a camera at a random spot in a 3 m cubic room, looking at a random
point of it at least 1 m away (7-Scenes' 640 x 480 camera, fx = fy = 585); the room's
random 3-D points in view (up to --points of them, at least 0.3 m ahead) are
projected, every pixel gets Gaussian noise (--noise-px) and a share (--outliers) is
replaced by uniform random pixels, as wrong matches would be. Both solvers see the
same correspondences with the same inlier threshold (--max-error) and the same rule
for success (a pose with at least --min-inliers inliers):

- poselib: relocfw.structure.solve_absolute_pose (PoseLib's P3P LO-RANSAC and Cauchy
  refinement, the conversion to a camera-to-world Pose included);
- pycolmap: pycolmap.estimate_and_refine_absolute_pose (COLMAP's P3P LO-RANSAC and
  refinement), converted the same way.

Timing is round robin: both solvers on each problem in turn, the first one
alternating between problems, so a slow phase of the machine hits both alike. Each
solver's seed is fixed, so the errors repeat exactly; the times do not. Prints a
table, writes JSON.

    .venv/bin/python benchmarks/structure_solvers.py --problems 200
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from common import write_json  # benchmarks/, the script's own folder

from relocfw.core.camera import SEVENSCENES_DEFAULT, PinholeCamera
from relocfw.core.geometry import matrix_to_quaternion, orientation_error_deg
from relocfw.core.values import Pose
from relocfw.structure.absolute_pose import pose_of_world_to_camera, solve_absolute_pose

ROOM_METRES = 3.0
UP = np.array([0.0, 0.0, 1.0])  # the room's vertical; cameras are held upright


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation of an upright camera at `position` facing `target`:
    columns are the camera's x (right), y (down) and z (forward) in the world."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(-UP, forward)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.column_stack([right, down, forward])


def make_problem(
    seed: int, camera: PinholeCamera, points: int, noise_px: float, outliers: float
) -> tuple[Pose, np.ndarray, np.ndarray]:
    """(true camera-to-world pose, [N, 2] noisy pixels with outliers, [N, 3] points)."""
    rng = np.random.default_rng(seed)
    while True:
        position = rng.uniform(0.3, ROOM_METRES - 0.3, 3)
        target = rng.uniform(0.0, ROOM_METRES, 3)
        direction = target - position
        # At least 1 m to look at, and not straight up or down (no upright camera).
        if np.linalg.norm(direction) > 1.0 and abs(direction @ UP) < 0.9 * np.linalg.norm(
            direction
        ):
            break
    rotation = look_at(position, target)
    room = rng.uniform(0.0, ROOM_METRES, (50 * points, 3))
    in_camera = (room - position) @ rotation
    ahead = in_camera[:, 2] > 0.3
    pixels = camera.project(np.where(ahead[:, None], in_camera, 1.0))
    inside = (
        ahead
        & (pixels[:, 0] >= 0)
        & (pixels[:, 0] <= camera.width - 1)
        & (pixels[:, 1] >= 0)
        & (pixels[:, 1] <= camera.height - 1)
    )
    chosen = np.flatnonzero(inside)[:points]
    pixels = pixels[chosen] + rng.normal(0.0, noise_px, (len(chosen), 2))
    wrong = rng.random(len(chosen)) < outliers
    pixels[wrong] = rng.uniform([0, 0], [camera.width, camera.height], (int(wrong.sum()), 2))
    return Pose(position, matrix_to_quaternion(rotation)), pixels, room[chosen]


def poselib_solver(max_error: float, min_inliers: int) -> Callable:
    def solve(pixels: np.ndarray, points: np.ndarray, camera: PinholeCamera) -> Pose | None:
        return solve_absolute_pose(pixels, points, camera, max_error, min_inliers).pose

    return solve


def pycolmap_solver(max_error: float, min_inliers: int, seed: int) -> Callable:
    import pycolmap

    options = pycolmap.AbsolutePoseEstimationOptions()
    options.ransac.max_error = max_error
    options.ransac.random_seed = seed

    def solve(pixels: np.ndarray, points: np.ndarray, camera: PinholeCamera) -> Pose | None:
        colmap_camera = pycolmap.Camera(
            model="PINHOLE",
            width=camera.width,
            height=camera.height,
            params=[camera.fx, camera.fy, camera.cx, camera.cy],
        )
        result = pycolmap.estimate_and_refine_absolute_pose(pixels, points, colmap_camera, options)
        if result is None or result["num_inliers"] < min_inliers:
            return None
        world_to_camera = result["cam_from_world"].matrix()  # [3, 4]: [R | t]
        q = matrix_to_quaternion(world_to_camera[:, :3])
        return pose_of_world_to_camera(q, world_to_camera[:, 3])

    return solve


def summary(errors: list[tuple[float, float] | None], seconds: list[float]) -> dict:
    solved = np.array([e for e in errors if e is not None]).reshape(-1, 2)
    return {
        "solved": len(solved),
        "failed": len(errors) - len(solved),
        "median_position_m": float(np.median(solved[:, 0])) if len(solved) else None,
        "p90_position_m": float(np.percentile(solved[:, 0], 90)) if len(solved) else None,
        "median_rotation_deg": float(np.median(solved[:, 1])) if len(solved) else None,
        "p90_rotation_deg": float(np.percentile(solved[:, 1], 90)) if len(solved) else None,
        "median_ms": 1000 * float(np.median(seconds)),
        "mean_ms": 1000 * float(np.mean(seconds)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=int, default=200)
    parser.add_argument("--points", type=int, default=200, help="correspondences per problem")
    parser.add_argument("--noise-px", type=float, default=1.0)
    parser.add_argument("--outliers", type=float, default=0.4, help="share of wrong matches")
    parser.add_argument("--max-error", type=float, default=8.0, help="inlier bound in pixels")
    parser.add_argument("--min-inliers", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/structure_solvers.json")
    )
    args = parser.parse_args()
    if args.problems < 1:
        parser.error("--problems must be at least 1")

    import poselib
    import pycolmap

    camera = SEVENSCENES_DEFAULT
    solvers = {
        "poselib": poselib_solver(args.max_error, args.min_inliers),
        "pycolmap": pycolmap_solver(args.max_error, args.min_inliers, args.seed),
    }
    problems = [
        make_problem(args.seed + i, camera, args.points, args.noise_px, args.outliers)
        for i in range(args.problems)
    ]
    for solve in solvers.values():  # warm-up: first-call costs are not a solve's
        solve(problems[0][1], problems[0][2], camera)

    errors: dict[str, list] = {name: [] for name in solvers}
    seconds: dict[str, list] = {name: [] for name in solvers}
    names = list(solvers)
    for index, (truth, pixels, points) in enumerate(problems):
        for name in names if index % 2 == 0 else names[::-1]:
            start = time.perf_counter()
            pose = solvers[name](pixels, points, camera)
            seconds[name].append(time.perf_counter() - start)
            errors[name].append(
                None
                if pose is None
                else (
                    float(np.linalg.norm(pose.position - truth.position)),
                    float(orientation_error_deg(pose.quaternion, truth.quaternion)),
                )
            )

    rows = {name: summary(errors[name], seconds[name]) for name in names}
    print(
        f"{args.problems} problems, {args.points} points, {args.noise_px} px noise, "
        f"{args.outliers:.0%} outliers, inlier bound {args.max_error} px"
    )
    print(f"{'solver':<10} {'solved':>7} {'median pos':>11} {'median rot':>11} {'median ms':>10}")
    for name, row in rows.items():
        position = row["median_position_m"]
        rotation = row["median_rotation_deg"]
        print(
            f"{name:<10} {row['solved']:>4}/{args.problems:<3}"
            f" {'-' if position is None else f'{1000 * position:.2f} mm':>10}"
            f" {'-' if rotation is None else f'{rotation:.4f} deg':>11}"
            f" {row['median_ms']:>10.2f}"
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
        "versions": {"poselib": poselib.__version__, "pycolmap": pycolmap.__version__},
        "machine": platform.processor() or platform.machine(),
        "timing": "round robin, the first solver alternating per problem; one thread each",
        "solvers": rows,
    }
    write_json(report, args.out)


if __name__ == "__main__":
    main()
