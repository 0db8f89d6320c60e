"""Test-split throughput: one query at a time against groups searched together.

Loads a model file written by `relocfw` (task=relocalize) and the test split of the
dataset it was built on (`--model`), or, without one, builds the paper's geometry as
benchmarks/query_cost.py does: a freshly initialised 224-pixel GoogLeNet (timing does
not depend on the weights), a k-means map of rendered 640 x 480 training views and
rendered test-lap queries. It then localizes the queries with each crop search twice: one
query at a time (`Relocalizer.localize`) and in groups whose searches run in one
loop, their candidate windows in merged forward passes (`Relocalizer.localize_many`,
relocfw.core.search_loop). The two modes take turns, `--repeats` times each, so a slow
moment of the machine does not land on one of them; each is timed by its median run.
Reports queries/s of both, the gain, and how far the two modes' answers are apart
(they should be the same up to float rounding). Prints a table, writes JSON.

    .venv/bin/python benchmarks/batched_throughput.py \\
        --model outputs/paper_geometry/model.relocfw --group 16
    .venv/bin/python benchmarks/batched_throughput.py --queries 32 --group 16
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch
from common import (  # benchmarks/, the script's own folder
    DEFAULT_CACHE,
    device_name,
    model_frames,
    render_views,
    with_search,
    write_json,
)
from shared_scoring import pose_difference

from relocfw import QueryOptions, Relocalizer, load_model
from relocfw.data.frames import read_images
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop

SETTINGS = {
    "centre": (CentreCrop, "plain"),
    "ga plain": (GeneticCropSearch, "plain"),
    "ga shared": (GeneticCropSearch, "shared"),
    "sweep plain": (SweepCrop, "plain"),
    "sweep shared": (SweepCrop, "shared"),
}


def timed(run) -> tuple[list, float]:
    start = time.perf_counter()
    answers = run()
    return answers, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, help="a model file; default: the paper's geometry")
    parser.add_argument("--map-images", type=int, default=60, help="without --model")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1, ...")
    parser.add_argument("--group", type=int, default=16, help="queries localized together")
    parser.add_argument("--batch-size", type=int, default=256, help="most windows per pass")
    parser.add_argument("--queries", type=int, default=0, help="first N test images; 0: all")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each mode")
    parser.add_argument("--only", nargs="+", choices=sorted(SETTINGS), default=list(SETTINGS))
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/batched_throughput.json")
    )
    args = parser.parse_args()
    rows = []
    if args.model is not None:
        frames = model_frames(load_model(args.model), args.cache.expanduser())
        images = read_images(frames[: args.queries] if args.queries else frames, quiet=True)
    else:
        torch.manual_seed(0)
        network = PoseNet(input_size=224).eval()
        images, _ = render_views(args.queries or 32, -1)
        map_images, _ = render_views(args.map_images, 0)
    for name in args.only:
        crop, scoring = SETTINGS[name]
        if args.model is not None:
            loaded = load_model(
                args.model, args.device, {"batch_size": args.batch_size, "scoring": scoring}
            )
            relocalizer = with_search(loaded, crop())
        else:
            options = QueryOptions(batch_size=args.batch_size, scoring=scoring)
            index = KMeansIndex(k=min(40, args.map_images))
            relocalizer = Relocalizer(network, index, crop(), options, args.device)
            relocalizer.fit(map_images)
        relocalizer.localize_many(images[: args.group], args.group)  # warm-up
        single_runs, many_runs = [], []
        for _ in range(args.repeats):  # the two modes take turns
            single, seconds = timed(lambda r=relocalizer: [r.localize(i) for i in images])
            single_runs.append(seconds)
            many, seconds = timed(lambda r=relocalizer: r.localize_many(images, args.group))
            many_runs.append(seconds)
        single_s, many_s = float(np.median(single_runs)), float(np.median(many_runs))
        positions, angles = pose_difference([a.pose for a in many], [a.pose for a in single])
        same = [a.crop == b.crop for a, b in zip(many, single, strict=True)]
        rows.append(
            {
                "setting": name,
                "queries": len(images),
                "one_at_a_time_queries_per_second": len(images) / single_s,
                "batched_queries_per_second": len(images) / many_s,
                "gain": single_s / many_s,
                "one_at_a_time_seconds": single_runs,
                "batched_seconds": many_runs,
                "same_crop": float(np.mean(same)),
                "max_pose_difference_m": float(positions.max()),
                "max_pose_difference_deg": float(angles.max()),
            }
        )
        r = rows[-1]
        print(
            f"{name:<12} one at a time {r['one_at_a_time_queries_per_second']:7.2f} q/s, "
            f"groups of {args.group} {r['batched_queries_per_second']:7.2f} q/s "
            f"(x{r['gain']:.2f}); same crop {r['same_crop']:.0%}, "
            f"max difference {r['max_pose_difference_m']:.1e} m"
        )
    report = {
        "model": str(args.model) if args.model else "untrained PoseNet-224, rendered views",
        "image": list(images[0].shape[1::-1]),
        "input_size": int(relocalizer.backbone.input_size),
        "group": args.group,
        "batch_size": args.batch_size,
        "repeats": args.repeats,
        "torch_threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "device": device_name(args.device),
        "rows": rows,
    }
    write_json(report, args.out)


if __name__ == "__main__":
    main()
