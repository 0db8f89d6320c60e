"""Which camera and which depth reading agree with the colour images' own geometry.

On the shared Red Kitchen frames (../shared/data/7scenes-redkitchen: raw Kinect depth,
not registered to the colour images), pairs of colour images of one sequence,
--gap frames apart, are matched (RootSIFT, mutual nearest neighbours with the ratio
test: relocfw.structure.features / matching) and the matches triangulated from the
known poses (relocfw.structure.triangulation: both reprojection errors within 4 px,
rays at least --min-angle degrees apart). Each triangulated point is then set beside
the point depth gives the same keypoint of the first image:

- before:      triangulated with f = 585, depth read at the colour pixel, lifted with
               585 (what relocfw did while one camera stood for both sensors);
- unregistered: triangulated with the colour camera (525), depth read at the colour
               pixel and lifted with 585 (the depth camera's focal length, but the
               depth sensor's pixel taken for the colour sensor's);
- registered:  triangulated with 525, the depth map registered into the colour image
               (relocfw.structure.registration.register_depth with the Kinect's
               depth-to-colour transform) and lifted with 525.

Reported per row: the median ratio of triangulated range to depth range (distance from
the first camera; 1 when the two agree on scale), the median 3-D distance between the
two points, and how many keypoint pairs gave both. The depth is the reference that does
not depend on the focal length, so a ratio away from 1 says the colour camera's focal
length is wrong (range scales with f for small baselines). Also reported: the time to
register one 640 x 480 depth map.

The dataset's poses are used for the colour camera, as relocfw and the evaluation do
(KinectFusion tracked the depth sensor, so strictly they are its poses; the row
`registered_colour_poses` moves each pose by the inverse of the depth-to-colour
transform, as DSAC*'s setup does for its "calibrated" variant, to show what that
changes).

    .venv/bin/python benchmarks/depth_registration.py --pairs 60
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
from common import write_json  # benchmarks/, the script's own folder

from relocfw.core.camera import SEVENSCENES_COLOUR, SEVENSCENES_DEPTH, PinholeCamera
from relocfw.core.geometry import matrix_to_quaternion, quaternion_to_matrix
from relocfw.core.imaging import read_rgb
from relocfw.core.values import Pose
from relocfw.data.depth import read_depth
from relocfw.data.frames import Frame
from relocfw.data.sevenscenes import SevenScenes
from relocfw.structure.features import LocalFeatures, extract_rootsift
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.matching import mutual_nearest_neighbours
from relocfw.structure.registration import register_depth
from relocfw.structure.triangulation import triangulate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-redkitchen"
ROWS = ("before", "unregistered", "registered", "registered_colour_poses")


def colour_pose(pose: Pose, depth_to_colour: np.ndarray) -> Pose:
    """The colour sensor's pose when `pose` is the depth sensor's: P T^-1."""
    matrix = np.eye(4)
    matrix[:3, :3] = quaternion_to_matrix(pose.quaternion)
    matrix[:3, 3] = pose.position
    moved = matrix @ np.linalg.inv(depth_to_colour)
    return Pose(moved[:3, 3], matrix_to_quaternion(moved[:3, :3]))


def pair_rows(
    frame_a: Frame,
    frame_b: Frame,
    features: dict[str, LocalFeatures],
    registered: dict[str, np.ndarray],
    min_angle: float,
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per row: triangulated points, depth points of the same keypoints, the first
    camera's centre, and the depth-transfer error (px) of every match with depth."""
    a, b = features[frame_a.name], features[frame_b.name]
    matches = mutual_nearest_neighbours(a.descriptors, b.descriptors, 0.8)
    pixels_a, pixels_b = a.keypoints[matches[:, 0]], b.keypoints[matches[:, 1]]
    raw = read_depth(frame_a.depth_path)
    transform = frame_a.depth_to_colour
    setups = {
        # (triangulation camera, depth map, lifting camera, poses)
        "before": (SEVENSCENES_DEPTH, raw, SEVENSCENES_DEPTH, (frame_a.pose, frame_b.pose)),
        "unregistered": (SEVENSCENES_COLOUR, raw, SEVENSCENES_DEPTH, (frame_a.pose, frame_b.pose)),
        "registered": (
            SEVENSCENES_COLOUR,
            registered[frame_a.name],
            SEVENSCENES_COLOUR,
            (frame_a.pose, frame_b.pose),
        ),
        "registered_colour_poses": (
            SEVENSCENES_COLOUR,
            registered[frame_a.name],
            SEVENSCENES_COLOUR,
            (colour_pose(frame_a.pose, transform), colour_pose(frame_b.pose, transform)),
        ),
    }
    rows = {}
    for row, (camera, depth, lifting_camera, (pose_a, pose_b)) in setups.items():
        points, valid = triangulate(
            pixels_a, pixels_b, camera, pose_a, camera, pose_b, 4.0, min_angle
        )
        lifted = lift_keypoints(pixels_a, depth, lifting_camera, pose_a)
        has_depth = np.isfinite(lifted).all(axis=1)
        both = valid & has_depth
        # The depth point of every match with depth, projected into the second image
        # with the row's camera: how far from the keypoint it was matched to.
        rotation = quaternion_to_matrix(pose_b.quaternion)
        in_b = (lifted[has_depth] - pose_b.position) @ rotation
        transfer = np.linalg.norm(camera.project(in_b) - pixels_b[has_depth], axis=1)
        rows[row] = (points[both], lifted[both], pose_a.position, transfer)
    return rows


def summary(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]) -> dict:
    triangulated = np.concatenate([p[0] for p in parts])
    lifted = np.concatenate([p[1] for p in parts])
    centres = np.concatenate([np.repeat(p[2][None], len(p[0]), 0) for p in parts])
    ratio = np.linalg.norm(triangulated - centres, axis=1) / np.linalg.norm(
        lifted - centres, axis=1
    )
    distance = np.linalg.norm(triangulated - lifted, axis=1)
    transfer = np.concatenate([p[3] for p in parts])
    return {
        "depth_transfer_matches": int(len(transfer)),
        "median_depth_transfer_px": round(float(np.nanmedian(transfer)), 3),
        "points": int(len(distance)),
        "median_range_ratio": round(float(np.median(ratio)), 4),
        "range_ratio_p25_p75": [round(float(v), 4) for v in np.percentile(ratio, [25, 75])],
        "median_distance_m": round(float(np.median(distance)), 4),
        "share_within_5cm": round(float(np.mean(distance < 0.05)), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--pairs", type=int, default=60)
    parser.add_argument("--gap", type=int, default=20, help="frames between a pair's images")
    parser.add_argument("--min-angle", type=float, default=3.0)
    parser.add_argument("--max-features", type=int, default=1024)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "depth_registration.json"
    )
    args = parser.parse_args()

    frames = SevenScenes(str(args.data), "redkitchen").frames("train")
    by_name = {frame.name: frame for frame in frames}
    starts = [
        f
        for f in frames
        if f"{f.name.split('/')[0]}/frame-{int(f.name[-6:]) + args.gap:06d}" in by_name
    ]
    picks = [starts[int(round(i))] for i in np.linspace(0, len(starts) - 1, args.pairs)]
    pairs = [
        (a, by_name[f"{a.name.split('/')[0]}/frame-{int(a.name[-6:]) + args.gap:06d}"])
        for a in picks
    ]
    camera: PinholeCamera = pairs[0][0].camera
    assert camera == SEVENSCENES_COLOUR and pairs[0][0].depth_camera == SEVENSCENES_DEPTH

    features: dict[str, LocalFeatures] = {}
    registered: dict[str, np.ndarray] = {}
    register_ms = []
    coverage = []
    started = time.perf_counter()
    for frame in {f.name: f for pair in pairs for f in pair}.values():
        features[frame.name] = extract_rootsift(read_rgb(frame.image_path), args.max_features)
    for frame, _ in pairs:
        raw = read_depth(frame.depth_path)
        begin = time.perf_counter()
        registered[frame.name] = register_depth(
            raw, frame.depth_camera, frame.camera, frame.depth_to_colour
        )
        register_ms.append(1000 * (time.perf_counter() - begin))
        coverage.append(
            [float(np.isfinite(raw).mean()), float(np.isfinite(registered[frame.name]).mean())]
        )
    collected: dict[str, list] = {row: [] for row in ROWS}
    for frame_a, frame_b in pairs:
        for row, part in pair_rows(frame_a, frame_b, features, registered, args.min_angle).items():
            collected[row].append(part)
    baselines = [float(np.linalg.norm(a.pose.position - b.pose.position)) for a, b in pairs]
    report = {
        "data": str(args.data),
        "pairs": len(pairs),
        "gap_frames": args.gap,
        "median_baseline_m": round(float(np.median(baselines)), 4),
        "min_angle_deg": args.min_angle,
        "max_features": args.max_features,
        "rows": {row: summary(parts) for row, parts in collected.items()},
        "register_ms_median": round(float(np.median(register_ms)), 2),
        "register_ms_min": round(float(np.min(register_ms)), 2),
        "depth_coverage_raw_vs_registered": [
            round(float(v), 4) for v in np.median(np.array(coverage), axis=0)
        ],
        "seconds": round(time.perf_counter() - started, 1),
        "machine": platform.processor() or platform.machine(),
    }
    for row, values in report["rows"].items():
        print(
            f"{row:24s} points {values['points']:5d}  range ratio "
            f"{values['median_range_ratio']:.3f}  median distance "
            f"{values['median_distance_m']:.3f} m  within 5 cm {values['share_within_5cm']:.1%}"
            f"  depth transfer {values['median_depth_transfer_px']:.2f} px"
        )
    print(
        f"register_depth: {report['register_ms_median']} ms median per 640x480 map; "
        f"depth coverage raw / registered: {report['depth_coverage_raw_vs_registered']}"
    )
    write_json(report, args.out)


if __name__ == "__main__":
    main()
