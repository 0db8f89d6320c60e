"""Per-query time and network passes of the crop searches at the paper's geometry.

640 x 480 images (480-pixel crops, 160 offsets), 224-pixel GoogLeNet input, each crop
search with plain scoring (every candidate through the whole network) and shared
scoring (one trunk pass over the strip, see relocfw.core.window_pooling). Timing does not
depend on the weights, so the network is freshly initialised; the map is fitted on
descriptors of rendered training views. The plain sweep runs twice, at the default
`batch_size` (most windows per pass) and at 64, the default before it was measured
here. Prints a table, writes JSON.

    .venv/bin/python benchmarks/query_cost.py --queries 20
"""

from __future__ import annotations

import argparse
import platform
from pathlib import Path

import numpy as np
import torch
from common import render_views, write_json  # benchmarks/, the script's own folder

from relocfw import QueryOptions, Relocalizer
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
    default = QueryOptions().batch_size
    methods = (
        ("centre", CentreCrop(), "plain", default),
        ("ga", GeneticCropSearch(), "plain", default),
        ("sweep", SweepCrop(), "plain", default),
        ("sweep", SweepCrop(), "plain", 64),
        ("ga", GeneticCropSearch(), "shared", default),
        ("sweep", SweepCrop(), "shared", default),
    )
    relocalizers = []
    for _, crop, scoring, batch_size in methods:
        index = KMeansIndex(k=min(40, args.map_images))
        options = QueryOptions(batch_size=batch_size, scoring=scoring)
        relocalizer = Relocalizer(backbone, index, crop, options)
        relocalizer.fit(map_images)
        relocalizer.localize(queries[0])  # warm-up: allocator, thread pool
        relocalizers.append(relocalizer)
    # Round robin, each query through every method in turn, and medians: a slow
    # moment of the machine then lands on all methods alike instead of on one.
    answers = [[] for _ in methods]
    for query in queries:
        for found, relocalizer in zip(answers, relocalizers, strict=True):
            found.append(relocalizer.localize(query))
    rows = [
        {
            "search": name,
            "scoring": scoring,
            "batch_size": batch_size,
            "ms_per_query": 1000 * float(np.median([a.seconds for a in found])),
            "mean_ms_per_query": 1000 * float(np.mean([a.seconds for a in found])),
            "crops_scored": float(np.mean([a.evaluations for a in found])),
            "network_passes": float(np.mean([a.network_passes for a in found])),
        }
        for (name, _, scoring, batch_size), found in zip(methods, answers, strict=True)
    ]
    centre = rows[0]["ms_per_query"]
    for row in rows:
        row["times_centre"] = row["ms_per_query"] / centre
    print(
        f"{'search':<8} {'scoring':<8} {'batch':>5} {'median ms':>9} {'crops':>6} "
        f"{'passes':>7} {'x centre':>9}"
    )
    for row in rows:
        print(
            f"{row['search']:<8} {row['scoring']:<8} {row['batch_size']:>5} "
            f"{row['ms_per_query']:>9.1f} "
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
