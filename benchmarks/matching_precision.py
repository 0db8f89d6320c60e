"""Matching in reduced precision: does bfloat16 keep the same matches, and is it faster?

The structure stage matches a query's RootSIFT against its keyframes' in one matrix
product (relocfw.structure.matching: ||q||^2 + ||c||^2 - 2 q c^T, then mutual nearest
neighbours with Lowe's ratio test). Here the product runs in float32 (what relocfw
does) and in bfloat16 (inputs rounded to 8 bits of mantissa, the norms kept in
float32), on real Red Kitchen frames: each query (evenly spread over the test
sequences 2, 4, 6) against its `--keyframes` nearest training frames (sequences 1, 3,
5, 7) by ground-truth position, features at `--image-scale` as refine=features
extracts them, map descriptors on their stored uint8 grid. Reported: the share of
float32's matches that bfloat16 also finds, the matches it adds, and the median ms
of each (the two precisions alternate query by query, so a slow spell of the
machine hits both).

    .venv/bin/python benchmarks/matching_precision.py --queries 40 --threads 2
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from common import write_json  # benchmarks/, the script's own folder
from structure_query import TEST_SEQUENCES, TRAIN_SEQUENCES, frames_of, read_rgb_cv2, set_threads

from relocfw.structure.features import extract_rootsift
from relocfw.structure.matching import matches_of_distances, squared_distances
from relocfw.structure.structure_map import on_descriptor_grid

PRECISIONS = {"float32": torch.float32, "bfloat16": torch.bfloat16}


def parse_arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data/7scenes-redkitchen"))
    parser.add_argument("--scene", default="redkitchen")
    parser.add_argument("--queries", type=int, default=40)
    parser.add_argument("--keyframes", type=int, default=10)
    parser.add_argument("--max-features", type=int, default=1024)
    parser.add_argument("--image-scale", type=float, default=0.5)
    parser.add_argument("--ratio", type=float, default=0.8)
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per query")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/matching_precision.json")
    )
    return parser.parse_args()


def matches(query: torch.Tensor, candidates: torch.Tensor, ends: list[int], ratio: float, dtype):
    """Per keyframe the (query, keyframe keypoint) matches, as matching.py finds them
    but with the product in `dtype`; a set of (keyframe, query, keypoint) triples."""
    if dtype == torch.float32:
        distances = squared_distances(query, candidates)  # relocfw's own
    else:
        query_norms = (query * query).sum(dim=1, keepdim=True)
        candidate_norms = (candidates * candidates).sum(dim=1)[None, :]
        product = (query.to(dtype) @ candidates.to(dtype).T).to(torch.float32)
        distances = (query_norms + candidate_norms - 2.0 * product).clamp_(min=0.0)
    found, start = set(), 0
    for number, end in enumerate(ends):
        pairs = matches_of_distances(distances[:, start:end], ratio)
        found |= {(number, int(q), int(c)) for q, c in pairs}
        start = end
    return found


def main() -> None:
    args = parse_arguments()
    set_threads(args.threads)
    scene = args.data / args.scene
    if not scene.is_dir():
        raise SystemExit(f"no scene folder {scene}")
    train = frames_of(scene, TRAIN_SEQUENCES)
    test = frames_of(scene, TEST_SEQUENCES)
    picks = np.linspace(0, len(test) - 1, min(args.queries, len(test))).round().astype(int)
    positions = np.array([frame.pose.position for frame in train])
    kept, added, total = 0, 0, 0
    seconds = {name: [] for name in PRECISIONS}
    cache: dict[int, np.ndarray] = {}
    for turn, index in enumerate(picks.tolist()):
        frame = test[index]
        query = extract_rootsift(read_rgb_cv2(frame.colour), args.max_features, args.image_scale)
        nearest = np.argsort(np.linalg.norm(positions - frame.pose.position, axis=1))
        descriptors = []
        for k in nearest[: args.keyframes].tolist():
            if k not in cache:
                image = read_rgb_cv2(train[k].colour)
                features = extract_rootsift(image, args.max_features, args.image_scale)
                cache[k] = on_descriptor_grid(features).descriptors
            descriptors.append(cache[k])
        ends = np.cumsum([len(d) for d in descriptors]).tolist()
        candidates = torch.from_numpy(np.concatenate(descriptors))
        query_t = torch.from_numpy(np.array(query.descriptors))
        names = list(PRECISIONS) if turn % 2 == 0 else list(PRECISIONS)[::-1]
        found = {}
        with torch.inference_mode():
            for name in names:
                times = []
                for _ in range(args.repeats):
                    start = time.perf_counter()
                    found[name] = matches(query_t, candidates, ends, args.ratio, PRECISIONS[name])
                    times.append(time.perf_counter() - start)
                seconds[name].append(float(np.median(times)))
        exact, reduced = found["float32"], found["bfloat16"]
        kept += len(exact & reduced)
        added += len(reduced - exact)
        total += len(exact)
    report = {
        "command": ["benchmarks/matching_precision.py", *sys.argv[1:]],
        "queries": len(picks),
        "keyframes": args.keyframes,
        "image_scale": args.image_scale,
        "max_features": args.max_features,
        "threads": args.threads,
        "machine": platform.processor() or platform.machine(),
        "load_average_1min": os.getloadavg()[0],
        "float32_matches": total,
        "bfloat16_keeps_share": kept / max(total, 1),
        "bfloat16_added": added,
        "median_ms": {name: 1000 * float(np.median(s)) for name, s in seconds.items()},
        "torch": torch.__version__,
    }
    write_json(report, args.out)
    print(
        f"{len(picks)} queries x {args.keyframes} keyframes: bfloat16 keeps "
        f"{100 * report['bfloat16_keeps_share']:.2f}% of float32's {total} matches and adds "
        f"{added}; median ms float32 {report['median_ms']['float32']:.2f}, bfloat16 "
        f"{report['median_ms']['bfloat16']:.2f}"
    )


if __name__ == "__main__":
    main()
