"""Per-query time and network passes of the crop searches at the paper's geometry.

640 x 480 images (480-pixel crops, 160 offsets), 224-pixel GoogLeNet input, each crop
search with plain scoring (every candidate through the whole network) and shared
scoring (one trunk pass over the strip, see relocfw.window_pooling). Timing does not
depend on the weights, so the network is freshly initialised; the map is fitted on
descriptors of rendered training views. Prints a table, writes JSON.

    .venv/bin/python benchmarks/query_cost.py --queries 10 --out benchmarks/results/query_cost.json
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch
from common import render_views, write_json  # benchmarks/, the script's own folder

from relocfw import Relocalizer
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=10)
    parser.add_argument("--map-images", type=int, default=60)
    parser.add_argument("--input-size", type=int, default=224)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/query_cost.json"))
    args = parser.parse_args()
    torch.manual_seed(0)
    backbone = PoseNet(input_size=args.input_size).eval()
    queries, _ = render_views(args.queries, -1)
    map_images, _ = render_views(args.map_images, 0)
    rows = []
    for name, crop, scoring in (
        ("centre", CentreCrop(), "plain"),
        ("ga", GeneticCropSearch(), "plain"),
        ("sweep", SweepCrop(), "plain"),
        ("ga", GeneticCropSearch(), "shared"),
        ("sweep", SweepCrop(), "shared"),
    ):
        index = KMeansIndex(k=min(40, args.map_images))
        relocalizer = Relocalizer(backbone, index, crop, scoring=scoring)
        relocalizer.fit(map_images)
        relocalizer.localize(queries[0])  # warm-up: allocator, thread pool
        start = time.perf_counter()
        answers = [relocalizer.localize(q) for q in queries]
        seconds = (time.perf_counter() - start) / len(queries)
        rows.append(
            {
                "search": name,
                "scoring": scoring,
                "ms_per_query": 1000 * seconds,
                "crops_scored": float(np.mean([a.evaluations for a in answers])),
                "network_passes": float(np.mean([a.network_passes for a in answers])),
            }
        )
    centre = rows[0]["ms_per_query"]
    for row in rows:
        row["times_centre"] = row["ms_per_query"] / centre
    print(
        f"{'search':<8} {'scoring':<8} {'ms/query':>9} {'crops':>6} {'passes':>7} {'x centre':>9}"
    )
    for row in rows:
        print(
            f"{row['search']:<8} {row['scoring']:<8} {row['ms_per_query']:>9.1f} "
            f"{row['crops_scored']:>6.1f} {row['network_passes']:>7.2f} {row['times_centre']:>9.2f}"
        )
    report = {
        "geometry": {"image": [640, 480], "crop": 480, "input": args.input_size},
        "queries": args.queries,
        "torch_threads": torch.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
        "rows": rows,
    }
    write_json(report, args.out)


if __name__ == "__main__":
    main()
