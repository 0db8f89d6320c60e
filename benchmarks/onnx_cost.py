"""Per-query time of the centre crop with the network run by torch and by onnxruntime.

What a robot gains (or loses) by running the exported network (task=export) instead
of torch: the same pipeline (640 x 480 views, centre crop, k-means map), once with
the torch backbone and once with OnnxBackbone on the CPU, both on torch's thread
count. Timing does not depend on the weights, so the PoseNet is freshly initialised.
Each query goes through both backends in turn (round robin) after a warm-up, and
the median over queries is reported. Prints a table, writes JSON.

    .venv/bin/python benchmarks/onnx_cost.py --queries 50
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime
import torch
from common import render_views, write_json  # benchmarks/, the script's own folder

from relocfw import Relocalizer
from relocfw.model.onnx_backbone import onnx_relocalizer
from relocfw.model.onnx_export import OPSET, export_onnx
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=3, help="untimed queries per backend")
    parser.add_argument("--map-images", type=int, default=20)
    parser.add_argument("--input-size", type=int, default=224)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/onnx_cost.json"))
    args = parser.parse_args()
    torch.manual_seed(0)
    backbone = PoseNet(input_size=args.input_size).eval()
    queries, _ = render_views(args.queries, -1)
    map_images, _ = render_views(args.map_images, 0)
    relocalizer = Relocalizer(backbone, KMeansIndex(k=min(40, args.map_images)), CentreCrop())
    relocalizer.fit(map_images)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "posenet.onnx"
        started = time.perf_counter()
        export_onnx(backbone, path)
        export_seconds = time.perf_counter() - started
        onnx_megabytes = path.stat().st_size / 2**20
        # The session holds the graph in memory: the file may go with the folder.
        backends = {"torch": relocalizer, "onnx": onnx_relocalizer(relocalizer, path)}
    for each in backends.values():
        for _ in range(args.warmup):
            each.localize(queries[0])  # allocator, thread pools, onnxruntime's first run
    # Round robin and medians: a slow moment of the machine lands on both alike.
    answers = {name: [] for name in backends}
    for query in queries:
        for name, each in backends.items():
            answers[name].append(each.localize(query))
    difference = max(
        float(np.max(np.abs(a.pose.position - b.pose.position)))
        for a, b in zip(answers["torch"], answers["onnx"], strict=True)
    )
    rows = [
        {
            "backend": name,
            "ms_per_query": 1000 * float(np.median([a.seconds for a in found])),
            "mean_ms_per_query": 1000 * float(np.mean([a.seconds for a in found])),
        }
        for name, found in answers.items()
    ]
    for row in rows:
        row["times_torch"] = row["ms_per_query"] / rows[0]["ms_per_query"]
    print(f"{'backend':<8} {'median ms':>9} {'mean ms':>8} {'x torch':>8}")
    for row in rows:
        print(
            f"{row['backend']:<8} {row['ms_per_query']:>9.1f} "
            f"{row['mean_ms_per_query']:>8.1f} {row['times_torch']:>8.2f}"
        )
    print(f"largest position difference between the backends: {difference:.2e} m")
    report = {
        "geometry": {"image": [640, 480], "crop": 480, "input": args.input_size},
        "search": "centre",
        "queries": args.queries,
        "warmup": args.warmup,
        "torch_threads": torch.get_num_threads(),
        "torch_version": torch.__version__,
        "onnxruntime_version": onnxruntime.__version__,
        "opset": OPSET,
        "export_seconds": export_seconds,
        "onnx_megabytes": onnx_megabytes,
        "max_position_difference_m": difference,
        "machine": platform.processor() or platform.machine(),
        "rows": rows,
    }
    write_json(report, args.out)


if __name__ == "__main__":
    main()
