"""Do Red Kitchen's seven blocks agree on where things are? Each query solved against
one other block's depth map at a time.

The shared Red Kitchen frames are seven consecutive 100-frame blocks of ONE
KinectFusion recording (../shared/data/7scenes-redkitchen/README.md), and the near
split answers blocks 2, 4 and 6 from blocks 1, 3, 5 and 7. If KinectFusion's poses
drift along the recording, a block's depth points sit a few cm away, in the dataset's
world, from where a block recorded minutes later puts the same surface, and a query
solved exactly against them still scores a few cm of error: a floor under every
structure row's "within 5 cm" that no map or retrieval can lift.

One depth map (relocfw.structure.build_from_depth: RootSIFT at --image-scale,
registered depth, the colour camera) is built over every --step-th frame of all seven
blocks. Each --query-step-th frame of a block is then solved (localize_against,
PoseLib LO-RANSAC, the refiner's defaults) against the --keyframes map images of ONE
block nearest its ground-truth pose (an oracle retrieval: the rows compare blocks, not
retrieval), for every block: its own too, without the frames within --exclude frames
of the query (the control: a block agrees with itself up to KinectFusion's local
drift). Only solves whose nearest keyframe stands within --near metres of the query
count, so a block that saw the place from elsewhere does not pass for disagreement.
Reported per (query block, map block): the counted solves, the median position
error, the share within 5 cm / 5 deg, and the length of the median error vector
(answer minus truth, world frame, per axis): near the median error when the block
pair disagrees by a common shift, near 0 when errors scatter. Summarised by how far
apart the two blocks are in the recording (0: the same block; 1: neighbours).

    .venv/bin/python benchmarks/block_consistency.py --out benchmarks/results/block_consistency.json
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
from common import LazyViews, write_json  # benchmarks/, the script's own folder

from relocfw.core.geometry import orientation_error_deg
from relocfw.core.imaging import read_rgb
from relocfw.data.pseudo_ground_truth import read_pseudo_ground_truth
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.structure import build_from_depth, keyframes_by_pose, localize_against
from relocfw.structure.features import extract_rootsift

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-redkitchen"
BLOCKS = range(1, 8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--step", type=int, default=2, help="every step-th frame in the map")
    parser.add_argument("--query-step", type=int, default=10, help="every n-th frame a query")
    parser.add_argument("--keyframes", type=int, default=10)
    parser.add_argument("--image-scale", type=float, default=0.5)
    parser.add_argument("--exclude", type=int, default=10, help="own-block frames left out")
    parser.add_argument("--near", type=float, default=0.3, help="nearest keyframe, metres")
    parser.add_argument("--max-features", type=int, default=1024)
    parser.add_argument(
        "--pgt",
        type=Path,
        default=None,
        help="a pseudo-ground-truth file (dataset.pgt) for the poses and cameras, e.g. "
        "pgt/redkitchen_sfm.txt: the blocks' agreement under that reference",
    )
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if not DATA.is_dir():
        raise SystemExit(f"{DATA} is absent")

    reference = read_pseudo_ground_truth(args.pgt) if args.pgt else None
    frames = {
        block: load_sevenscenes(DATA, "redkitchen", "train", sequences=[block], reference=reference)
        for block in BLOCKS
    }
    mapped = [(block, f) for block in BLOCKS for f in frames[block][:: args.step]]
    started = time.perf_counter()
    structure = build_from_depth(
        LazyViews([f for _, f in mapped]), args.max_features, True, args.image_scale
    )
    build_seconds = time.perf_counter() - started
    block_of = np.array([block for block, _ in mapped])
    index_of = np.array([int(f.name.rsplit("-", 1)[-1]) for _, f in mapped])

    pairs = []
    for query_block in BLOCKS:
        for frame in frames[query_block][:: args.query_step]:
            features = extract_rootsift(
                read_rgb(frame.image_path), args.max_features, args.image_scale
            )
            number = int(frame.name.rsplit("-", 1)[-1])
            for map_block in BLOCKS:
                members = np.flatnonzero(block_of == map_block)
                if map_block == query_block:
                    members = members[np.abs(index_of[members] - number) > args.exclude]
                if not len(members):
                    continue  # --exclude left the query's own block empty
                poses = [structure.poses[i] for i in members]
                chosen = members[keyframes_by_pose(poses, frame.pose, args.keyframes)]
                nearest = np.linalg.norm(structure.poses[chosen[0]].position - frame.pose.position)
                if nearest > args.near:
                    continue
                answer = localize_against(
                    structure,
                    None,
                    frame.camera,
                    chosen.tolist(),
                    query_features=features,
                    image_scale=args.image_scale,
                )
                shift = (
                    answer.pose.position - frame.pose.position
                    if answer.success
                    else np.full(3, np.nan)
                )
                angle = (
                    orientation_error_deg(answer.pose.quaternion, frame.pose.quaternion)
                    if answer.success
                    else np.nan
                )
                pairs.append((query_block, map_block, shift, angle))

    rows = []
    for query_block in BLOCKS:
        for map_block in BLOCKS:
            mine = [(s, a) for q, m, s, a in pairs if (q, m) == (query_block, map_block)]
            if not mine:
                continue
            shifts = np.array([s for s, _ in mine])
            angles = np.array([a for _, a in mine])
            solved = np.isfinite(shifts).all(axis=1)
            errors = np.linalg.norm(shifts[solved], axis=1)
            # Strictly within, as relocfw's bands count (relocfw.report.evaluation).
            within = (np.linalg.norm(np.nan_to_num(shifts, nan=np.inf), axis=1) < 0.05) & (
                np.nan_to_num(angles, nan=np.inf) < 5.0
            )
            rows.append(
                {
                    "query_block": query_block,
                    "map_block": map_block,
                    "apart": abs(query_block - map_block),
                    "queries": len(mine),
                    "solved": int(solved.sum()),
                    "median_position_m": float(np.median(errors)) if solved.any() else None,
                    "within_5cm_5deg": float(within.mean()),
                    "median_shift_m": float(np.linalg.norm(np.median(shifts[solved], axis=0)))
                    if solved.any()
                    else None,
                }
            )
    by_apart = {}
    for apart in range(0, 7):
        chosen = [r for r in rows if r["apart"] == apart and r["median_position_m"] is not None]
        if chosen:
            by_apart[apart] = {
                "pairs": len(chosen),
                "median_of_median_position_m": float(
                    np.median([r["median_position_m"] for r in chosen])
                ),
                "median_of_median_shift_m": float(np.median([r["median_shift_m"] for r in chosen])),
                "queries": int(sum(r["queries"] for r in chosen)),  # counted, solved or not
                "mean_within_5cm_5deg": float(np.mean([r["within_5cm_5deg"] for r in chosen])),
            }
    report = {
        "settings": vars(args) | {"out": str(args.out), "pgt": str(args.pgt) if args.pgt else None},
        "pose_reference": str(args.pgt) if args.pgt else "the .pose.txt files (KinectFusion)",
        "machine": platform.processor() or platform.machine(),
        "map_images": len(mapped),
        "build_seconds": round(build_seconds, 1),
        "pairs": rows,
        "by_blocks_apart": by_apart,
    }
    write_json(report, args.out)
    print("blocks apart | pairs | queries | median position (m) | median shift (m) | 5 cm / 5 deg")
    for apart, row in by_apart.items():
        print(
            f"{apart} | {row['pairs']} | {row['queries']} | "
            f"{row['median_of_median_position_m']:.3f} | "
            f"{row['median_of_median_shift_m']:.3f} | {100 * row['mean_within_5cm_5deg']:.0f}%"
        )


if __name__ == "__main__":
    main()
