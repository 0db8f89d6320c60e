"""How query cost grows: with image size, with the GA's budget, with the map.

1. Image size (640 x 480, 1280 x 720, 1920 x 1080; 224-pixel input): ms/query and
   network passes of the centre crop, the plain and shared GA and the shared sweep.
   Timing does not depend on the weights, so the network is freshly initialised, nor
   on the content, so views rendered at 640 x 480 are resized to each size.
2. GA population x iterations at 640 x 480, plain scoring: ms/query and passes.
3. Map size, with real descriptors of a trained model (`--model`, a model file from
   `relocfw`): descriptors of many windows of its training images; fit time and
   the time of one lookup of a GA generation (10 descriptors) for k-means (k=40)
   and the exact index, at each map size.

Queries go round robin through the settings of a part, and medians are reported.
Prints tables, writes JSON.

    .venv/bin/python benchmarks/cost_scaling.py --queries 5 \\
        --model outputs/paper_geometry/model.relocfw
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from common import (  # benchmarks/, the script's own folder
    DEFAULT_CACHE,
    model_frames,
    render_views,
    write_json,
)

from relocfw import QueryOptions, Relocalizer, load_model
from relocfw.core.interfaces import crop_at, crop_side_and_span
from relocfw.data.frames import read_images
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop

SIZES = ((640, 480), (1280, 720), (1920, 1080))
GA_BUDGETS = ((10, 3), (20, 3), (10, 6), (20, 6), (40, 6))


def round_robin(settings: dict[str, Relocalizer], queries: list[np.ndarray]) -> list[dict]:
    for relocalizer in settings.values():
        relocalizer.localize(queries[0])  # warm-up
    found: dict[str, list] = {name: [] for name in settings}
    for query in queries:
        for name, relocalizer in settings.items():
            found[name].append(relocalizer.localize(query))
    return [
        {
            "setting": name,
            "ms_per_query": 1000 * float(np.median([a.seconds for a in answers])),
            "network_passes": float(np.mean([a.network_passes for a in answers])),
            "crops_scored": float(np.mean([a.evaluations for a in answers])),
        }
        for name, answers in found.items()
    ]


def resized(images: list[np.ndarray], width: int, height: int) -> list[np.ndarray]:
    return [cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR) for image in images]


def image_sizes(backbone: PoseNet, count: int, map_images: int) -> list[dict]:
    # Rendered once at 640 x 480 and resized: cost depends on the pixel count, not on
    # the content, and rendering at 1920 x 1080 would take far longer than the timing.
    base_queries, _ = render_views(count, -1)
    base_views, _ = render_views(map_images, 0)
    rows = []
    for width, height in SIZES:
        queries = resized(base_queries, width, height)
        views = resized(base_views, width, height)
        k = min(40, map_images)
        shared = QueryOptions(scoring="shared")
        settings = {
            "centre": Relocalizer(backbone, KMeansIndex(k=k), CentreCrop()),
            "ga plain": Relocalizer(backbone, KMeansIndex(k=k), GeneticCropSearch()),
            "ga shared": Relocalizer(backbone, KMeansIndex(k=k), GeneticCropSearch(), shared),
            "sweep shared": Relocalizer(backbone, KMeansIndex(k=k), SweepCrop(), shared),
        }
        for relocalizer in settings.values():
            relocalizer.fit(views)
        for row in round_robin(settings, queries):
            rows.append({"image": [width, height], **row})
            print(
                f"{width}x{height} {row['setting']:<13} {row['ms_per_query']:8.1f} ms "
                f"{row['network_passes']:6.2f} passes {row['crops_scored']:6.1f} crops"
            )
    return rows


def ga_budgets(backbone: PoseNet, count: int, map_images: int) -> list[dict]:
    queries, _ = render_views(count, -1)
    views, _ = render_views(map_images, 0)
    settings = {}
    for population, iterations in GA_BUDGETS:
        relocalizer = Relocalizer(
            backbone,
            KMeansIndex(k=min(40, map_images)),
            GeneticCropSearch(population=population, iterations=iterations),
        )
        relocalizer.fit(views)
        settings[f"{population} x {iterations + 1}"] = relocalizer
    rows = round_robin(settings, queries)
    for row, (population, iterations) in zip(rows, GA_BUDGETS, strict=True):
        row.update(population=population, iterations=iterations)
        print(
            f"GA population {population:>3} x {iterations + 1} generations: "
            f"{row['ms_per_query']:8.1f} ms {row['network_passes']:6.2f} passes"
        )
    return rows


def real_descriptors(model: Path, cache: Path, most: int) -> np.ndarray:
    """Up to `most` descriptors of the sweep windows of the model's training images."""
    relocalizer = load_model(model)
    images = read_images(model_frames(relocalizer, cache, "train"), quiet=True)
    rng = np.random.default_rng(0)
    parts, total = [], 0
    for i in rng.permutation(len(images)):
        strip = relocalizer.scorer.strip(images[i])  # the pipeline's own, crop_scale included
        _, span = crop_side_and_span(strip.width, strip.height)
        corners = list(
            dict.fromkeys(
                strip.window(crop_at(o, strip.width, strip.height)) for o in range(span + 1)
            )
        )
        windows = torch.stack([strip.cut(c) for c in corners])
        parts.append(relocalizer.scorer.forward(windows).features)
        total += len(corners)
        if total >= most:
            break
    return np.concatenate(parts)[:most]


def map_sizes(descriptors: np.ndarray, sizes: list[int], repeats: int = 20) -> list[dict]:
    rng = np.random.default_rng(1)
    rows = []
    for size in sizes:
        if size > len(descriptors):
            continue
        chosen = descriptors[rng.choice(len(descriptors), size, replace=False)]
        queries = descriptors[rng.choice(len(descriptors), 10, replace=False)]
        for name, index in (
            ("kmeans k=40", KMeansIndex(k=min(40, size))),
            ("exhaustive", ExhaustiveIndex()),
        ):
            start = time.perf_counter()
            index.fit(chosen)
            fit = time.perf_counter() - start
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                index.distance(queries)
                times.append(time.perf_counter() - start)
            rows.append(
                {
                    "map_descriptors": size,
                    "index": name,
                    "fit_seconds": fit,
                    "lookup_ms_10_descriptors": 1000 * float(np.median(times)),
                }
            )
            print(
                f"map {size:>7} {name:<12} fit {fit:8.2f} s, "
                f"lookup of 10 {rows[-1]['lookup_ms_10_descriptors']:8.3f} ms"
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=5)
    parser.add_argument("--map-images", type=int, default=60)
    parser.add_argument("--input-size", type=int, default=224)
    parser.add_argument("--model", type=Path, help="model file for part 3 (real descriptors)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    parser.add_argument("--map-sizes", type=int, nargs="+", default=[100, 1000, 5000])
    parser.add_argument("--only", nargs="+", choices=["sizes", "ga", "map"], default=None)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/cost_scaling.json"))
    args = parser.parse_args()
    parts = set(args.only or ["sizes", "ga", "map"])
    torch.manual_seed(0)
    backbone = PoseNet(input_size=args.input_size).eval()
    report: dict = {
        "input_size": args.input_size,
        "queries": args.queries,
        "torch_threads": torch.get_num_threads(),
        "machine": platform.machine(),
    }
    if "sizes" in parts:
        report["image_sizes"] = image_sizes(backbone, args.queries, args.map_images)
    if "ga" in parts:
        report["ga_budgets"] = ga_budgets(backbone, args.queries, args.map_images)
    if "map" in parts and args.model is not None:
        descriptors = real_descriptors(args.model, args.cache.expanduser(), max(args.map_sizes))
        report["map_model"] = str(args.model)
        report["map_sizes"] = map_sizes(descriptors, args.map_sizes)
    write_json(report, args.out)


if __name__ == "__main__":
    main()
