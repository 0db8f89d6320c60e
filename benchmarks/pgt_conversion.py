"""The published DSLAM reference against relocfw's own conversion of 7-Scenes' poses.

The DSLAM file of Brachmann et al. (ICCV 2021; the shared copy's pgt/redkitchen_dslam.txt)
holds 7-Scenes' KinectFusion poses moved to the colour camera. relocfw reads the
`.pose.txt` files either as the colour camera's (`dataset.poses_of=colour`, the
default) or as the depth sensor's, moved to the colour camera by its own depth-to-
colour calibration (`poses_of=depth`, relocfw.data.sevenscenes.SEVENSCENES_DEPTH_TO_COLOUR).
For every frame of the recording this script sets both beside the file's colour pose
(position and rotation difference), and recovers the one fixed transform that takes a
`.pose.txt` pose to the file's (the mean of the per-frame transforms) to compare it
with relocfw's calibration. The SfM file's poses live in another world frame, so they
are not compared here (see docs/results/families.md for what that reference does to
the results).

    .venv/bin/python benchmarks/pgt_conversion.py \
        --data ../shared/data/7scenes-redkitchen --out benchmarks/results/pgt_conversion.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from common import write_json  # benchmarks/, the script's own folder

from relocfw.core.geometry import (
    matrix_to_quaternion,
    mean_quaternion,
    pose_to_matrix,
    quaternion_to_matrix,
)
from relocfw.core.sensor_poses import colour_pose
from relocfw.data.pseudo_ground_truth import read_pseudo_ground_truth
from relocfw.data.sevenscenes import SEVENSCENES_DEPTH_TO_COLOUR, load_sevenscenes


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """The angle of a rotation matrix, degrees."""
    cosine = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosine)))


def differences(estimates: list[np.ndarray], references: list[np.ndarray]) -> dict:
    """Median, mean and largest position (m) and rotation (deg) difference of 4x4
    camera-to-world poses against the references."""
    pairs = list(zip(estimates, references, strict=True))
    positions = [np.linalg.norm(e[:3, 3] - r[:3, 3]) for e, r in pairs]
    angles = [rotation_angle_deg(e[:3, :3].T @ r[:3, :3]) for e, r in pairs]
    return {
        "position_m": {
            "median": float(np.median(positions)),
            "mean": float(np.mean(positions)),
            "max": float(np.max(positions)),
        },
        "rotation_deg": {
            "median": float(np.median(angles)),
            "mean": float(np.mean(angles)),
            "max": float(np.max(angles)),
        },
    }


def transform_summary(rotation: np.ndarray, translation: np.ndarray) -> dict:
    """A rigid transform's translation (m, its length) and rotation angle (deg)."""
    return {
        "translation_m": translation.tolist(),
        "translation_length_m": float(np.linalg.norm(translation)),
        "rotation_deg": rotation_angle_deg(rotation),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="the 7scenes-redkitchen folder")
    parser.add_argument("--scene", default="redkitchen")
    parser.add_argument("--sequences", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6, 7])
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    dslam_file = args.data / "pgt" / f"{args.scene}_dslam.txt"
    dslam = read_pseudo_ground_truth(dslam_file)
    from_file = load_sevenscenes(
        args.data, args.scene, "train", sequences=args.sequences, reference=dslam
    )
    as_depth = load_sevenscenes(
        args.data, args.scene, "train", sequences=args.sequences, poses_of="depth"
    )
    by_name = {frame.name: frame for frame in as_depth}
    names = [frame.name for frame in from_file if frame.name in by_name]
    file_poses = [pose_to_matrix(frame.pose) for frame in from_file if frame.name in by_name]
    pose_txt = [pose_to_matrix(by_name[name].pose) for name in names]
    converted = [
        pose_to_matrix(colour_pose(by_name[name].pose, by_name[name].pose_to_colour))
        for name in names
    ]
    # The per-frame transform from a .pose.txt pose to the file's colour pose, in the
    # depth sensor's frame: T = P_txt^-1 P_file (relocfw's is T_depth_to_colour^-1).
    per_frame = [np.linalg.inv(p) @ f for p, f in zip(pose_txt, file_poses, strict=True)]
    mean_rotation = quaternion_to_matrix(
        mean_quaternion(np.array([matrix_to_quaternion(t[:3, :3]) for t in per_frame]))
    )
    mean_translation = np.mean([t[:3, 3] for t in per_frame], axis=0)
    relocfw_transform = np.linalg.inv(SEVENSCENES_DEPTH_TO_COLOUR)
    spread = [np.linalg.norm(t[:3, 3] - mean_translation) for t in per_frame]
    report = {
        "data": str(args.data),
        "reference_file": str(dslam_file),
        "frames": len(names),
        "sequences": args.sequences,
        "pose_txt_as_colour_vs_file": differences(pose_txt, file_poses),
        "relocfw_poses_of_depth_vs_file": differences(converted, file_poses),
        "file_transform": {
            **transform_summary(mean_rotation, mean_translation),
            "translation_spread_max_m": float(np.max(spread)),
        },
        "relocfw_transform": transform_summary(relocfw_transform[:3, :3], relocfw_transform[:3, 3]),
        "rotation_between_the_two_deg": rotation_angle_deg(
            mean_rotation.T @ relocfw_transform[:3, :3]
        ),
        "translation_between_the_two_m": float(
            np.linalg.norm(mean_translation - relocfw_transform[:3, 3])
        ),
    }
    write_json(report, args.out)
    for key in ("pose_txt_as_colour_vs_file", "relocfw_poses_of_depth_vs_file"):
        row = report[key]
        print(
            f"{key}: median {row['position_m']['median'] * 100:.2f} cm, "
            f"{row['rotation_deg']['median']:.2f} deg"
        )
    print(f"file's transform: {report['file_transform']}")
    print(f"relocfw's: {report['relocfw_transform']}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
