"""Per-query time of every query path on torch, onnxruntime and onnxruntime int8.

The same pipeline (640 x 480 views of the synthetic room, k-means map of --map-images
views) localizes every query with each method on each engine, round robin (the order
rotates from query to query, so a slow phase of the machine hits every pair alike),
after --warmup untimed queries per pair. Reported per method and engine: the median
ms per query, its multiple of the same engine's centre crop (x centre), its speed-up
over torch, and how far its answers are from torch's (same crop, largest position
difference). Timing does not depend on the weights: networks are freshly initialised
(EfficientNet-Lite0 from its packaged ImageNet weights).

Geometries (--geometry): `paper` (GoogLeNet PoseNet, 224 px) and `real_cpu`
(EfficientNet-Lite0, 128 px, the real_cpu preset's network). Methods: centre crop,
the paper's GA and the exhaustive sweep scored plainly, the GA with shared scoring,
and Bayesian PoseNet's kendall variant with 40 Monte Carlo samples of the centre crop.

Engines on a CPU: torch, onnx (float32), ncnn (float32, where relocfw[ncnn] is
installed), onnx-int8 (onnx.int8=static: 7-bit weights, calibrated on the map views)
and, where the CPU has VNNI, onnx-int8-8bit (onnx.int8=static_8bit); for the plain
searches, onnx-int8-scout (query.scoring=scout with onnx.int8=static: the int8 graph
scores the candidates, the float32 graph answers the chosen crop) and
onnx-int8-scout-best3 (the same with query.rerank=3). With --device
cuda: torch, torch-amp (float16 autocast) and torch-compile.
--threads-study also times centre and plain GA at the paper geometry under every
combination of torch threads, onnxruntime intra-op threads and thread spinning.

    .venv/bin/python benchmarks/engine_cost.py --queries 12 --threads-study
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import os
import platform
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from common import device_name, render_views, write_json  # benchmarks/, the script's folder

from relocfw import Relocalizer
from relocfw.core.interfaces import Backbone
from relocfw.core.query_options import QueryOptions
from relocfw.core.values import PoseOutput
from relocfw.model.cpu_flags import int8_saturation_reason
from relocfw.model.ncnn_engine import ncnn_engine, ncnn_installed
from relocfw.model.onnx_engine import EngineOptions, onnx_engine
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop

CROP_SCALE = 1.142857  # PoseNet's 256 / 224, what every preset trains with
METHODS = ("centre", "ga plain", "sweep plain", "ga shared", "mc kendall x40")
CPU_ENGINES = (
    "torch",
    "onnx",
    "ncnn",
    "onnx-int8",
    "onnx-int8-8bit",
    "onnx-int8-scout",
    "onnx-int8-scout-best3",
)
# query.scoring=scout engines -> query.rerank (the best N scouted crops re-scored).
SCOUT_RERANK = {"onnx-int8-scout": 1, "onnx-int8-scout-best3": 3}
# query.scoring=scout changes how a search's candidates are scored: plain searches only.
SCOUTED_METHODS = ("ga plain", "sweep plain")
GPU_ENGINES = ("torch", "torch-amp", "torch-compile")


SIZES = {"paper": 224, "real_cpu": 128}


def network(
    geometry: str, variant: str = "head", samples: int = 0, size: int | None = None, width=1.0
) -> Backbone:
    """A freshly initialised network of the geometry (seeded: every engine gets the
    same weights); `size` and `width` shrink it for the plumbing test."""
    torch.manual_seed(0)
    size = size or SIZES[geometry]
    if geometry == "paper":
        backbone = PoseNet(size, width=width, dropout_variant=variant, mc_samples=samples)
    else:
        from relocfw.plugins.efficientnet_lite import EfficientNetLite0

        backbone = EfficientNetLite0(size, dropout_variant=variant, mc_samples=samples)
    backbone.set_crop_scale(CROP_SCALE)
    return backbone.eval()


class Autocast(Backbone):
    """A CUDA backbone run under float16 autocast (AMP) at inference: every pass the
    pipeline makes (plain, shared scoring's maps, Monte Carlo samples) goes through
    the inner network's own methods, whose test-time options it shares."""

    def __init__(self, inner: Backbone) -> None:
        super().__init__()
        self.inner = inner
        self.input_size, self.feature_dim = inner.input_size, inner.feature_dim
        self.channels_last = inner.channels_last
        self.test_time_options = tuple(inner.test_time_options)
        self.crop_scale.copy_(inner.crop_scale)

    @property
    def mc_samples(self) -> int:
        return int(getattr(self.inner, "mc_samples", 0))

    @mc_samples.setter
    def mc_samples(self, samples: int) -> None:
        self.inner.mc_samples = samples

    @property
    def shares_strip(self) -> bool:
        return self.inner.shares_strip

    def forward(self, images: torch.Tensor) -> PoseOutput:
        with torch.autocast("cuda", dtype=torch.float16):
            out = self.inner(images)
        return dataclasses.replace(
            out,
            positions=out.positions.float(),
            quaternions=out.quaternions.float(),
            features=out.features.float(),
        )

    def feature_maps(self, images: torch.Tensor) -> torch.Tensor:
        with torch.autocast("cuda", dtype=torch.float16):
            return self.inner.feature_maps(images).float()

    def describe_pooled(self, pooled: torch.Tensor) -> torch.Tensor:
        with torch.autocast("cuda", dtype=torch.float16):
            return self.inner.describe_pooled(pooled).float()


def on_engine(
    relocalizer: Relocalizer, engine: str, folder: Path, calibration: list, options: dict
) -> Relocalizer:
    """The fitted relocalizer with its network run by `engine` (same map)."""
    backbone = relocalizer.backbone
    owner = folder / f"{id(backbone)}.pt"
    if engine == "torch":
        return relocalizer
    if engine == "onnx":
        return relocalizer.replace(backbone=onnx_engine(backbone, owner, EngineOptions(**options)))
    if engine == "ncnn":
        return relocalizer.replace(backbone=ncnn_engine(backbone, owner, EngineOptions(**options)))
    if engine in ("onnx-int8", "onnx-int8-8bit"):
        mode = "static" if engine == "onnx-int8" else "static_8bit"
        settings = EngineOptions(int8=mode, **options)
        return relocalizer.replace(backbone=onnx_engine(backbone, owner, settings, calibration))
    if engine in SCOUT_RERANK:
        settings = EngineOptions(int8="static", scout=True, **options)
        scouting = relocalizer.options.replace(scoring="scout", rerank=SCOUT_RERANK[engine])
        return relocalizer.replace(
            backbone=onnx_engine(backbone, owner, settings, calibration), options=scouting
        )
    if engine == "torch-amp":
        return relocalizer.replace(backbone=Autocast(backbone))
    if engine == "torch-compile":
        compiled = torch.compile(backbone)
        compiled.eval()
        return relocalizer.replace(backbone=compiled)
    raise ValueError(f"unknown engine {engine}")


def method_pipeline(
    geometry: str, method: str, maps: list, args: argparse.Namespace
) -> Relocalizer:
    """The method's fitted torch pipeline."""
    search = {"centre": CentreCrop(), "sweep": SweepCrop()}.get(
        method.split()[0], GeneticCropSearch(seed=0)
    )
    shape = {"size": args.input_size, "width": args.width}
    if method.startswith("mc"):
        backbone, search = network(geometry, "kendall", 40, **shape), CentreCrop()
    else:
        backbone = network(geometry, **shape)
    scoring = "shared" if method.endswith("shared") else "plain"
    options = QueryOptions(batch_size=args.batch_size, scoring=scoring)
    index = KMeansIndex(k=min(40, len(maps)))
    relocalizer = Relocalizer(backbone, index, search, options, args.device)
    relocalizer.fit(maps)
    return relocalizer


@dataclass
class Pair:
    method: str
    engine: str
    relocalizer: Relocalizer
    threads: int | None = None  # torch threads while it runs (None: as they are)


def round_robin(pairs: list[Pair], queries: list, warmup: int) -> dict[tuple, list]:
    """Every pair localizes every query, in an order rotating from query to query."""
    for pair in pairs:
        for query in queries[:warmup]:
            run(pair, query)
    found: dict[tuple, list] = {(p.method, p.engine): [] for p in pairs}
    for number, query in enumerate(queries):
        shift = number % len(pairs)
        for pair in pairs[shift:] + pairs[:shift]:
            found[pair.method, pair.engine].append(run(pair, query))
    return found


def run(pair: Pair, query: np.ndarray):  # noqa: ANN201 - a Localization
    if pair.threads is not None:
        torch.set_num_threads(pair.threads)
    return pair.relocalizer.localize(query)


def summary(found: dict[tuple, list], engines: tuple[str, ...]) -> list[dict]:
    rows = []
    for (method, engine), answers in found.items():
        reference = found.get((method, engines[0]), answers)
        ms = 1000 * float(np.median([a.seconds for a in answers]))
        rows.append(
            {
                "method": method,
                "engine": engine,
                "ms_per_query": ms,
                "mean_ms_per_query": 1000 * float(np.mean([a.seconds for a in answers])),
                "network_passes": float(np.mean([a.network_passes for a in answers])),
                "same_crop_as_torch": float(
                    np.mean([a.crop == b.crop for a, b in zip(answers, reference, strict=True)])
                ),
                "max_position_difference_m": float(
                    max(
                        np.max(np.abs(a.pose.position - b.pose.position))
                        for a, b in zip(answers, reference, strict=True)
                    )
                ),
            }
        )
    by = {(r["method"], r["engine"]): r for r in rows}
    for row in rows:
        centre = by.get(("centre", row["engine"]))
        first = by.get((row["method"], engines[0]))
        row["x_centre"] = row["ms_per_query"] / centre["ms_per_query"] if centre else None
        row["speedup_over_torch"] = first["ms_per_query"] / row["ms_per_query"] if first else None
    return rows


def number(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def table(rows: list[dict], title: str, reference: str = "torch") -> str:
    lines = [
        f"\n{title}",
        f"| method | engine | ms/query | x centre | x faster than {reference} | same crop "
        "| max pos diff (m) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['engine']} | {r['ms_per_query']:.1f} | "
            f"{number(r['x_centre'])} | {number(r['speedup_over_torch'])} | "
            f"{100 * r['same_crop_as_torch']:.0f}% | {r['max_position_difference_m']:.1e} |"
        )
    return "\n".join(lines)


def geometry_run(geometry: str, args: argparse.Namespace, folder: Path) -> list[dict]:
    engines = GPU_ENGINES if args.device.startswith("cuda") else CPU_ENGINES
    if int8_saturation_reason() is not None:  # no VNNI: 8-bit weights are refused
        engines = tuple(e for e in engines if e != "onnx-int8-8bit")
    if not ncnn_installed():
        print('ncnn or pnnx is not installed ("relocfw[ncnn]"): its rows are left out')
        engines = tuple(e for e in engines if e != "ncnn")
    engines = tuple(e for e in engines if e in args.engines) or engines
    maps, _ = render_views(args.map_images, 0, *args.view_size)
    queries, _ = render_views(args.queries + args.warmup, -1, *args.view_size)
    pairs = []
    for method in args.methods:
        base = method_pipeline(geometry, method, maps, args)
        for engine in engines:
            if engine in SCOUT_RERANK and method not in SCOUTED_METHODS:
                continue
            started = time.perf_counter()
            pairs.append(Pair(method, engine, on_engine(base, engine, folder, maps, {})))
            print(f"{geometry} {method} {engine}: ready in {time.perf_counter() - started:.1f} s")
    rows = summary(round_robin(pairs, queries, args.warmup), engines)
    width, height = args.view_size
    print(table(rows, f"{geometry}: {width} x {height} views, {args.queries} queries"))
    return rows


def threads_study(args: argparse.Namespace, folder: Path) -> dict[str, list[dict]]:
    """centre and plain GA at the paper geometry: torch's and onnxruntime's thread
    counts in one round robin; then onnxruntime's thread spinning in a second one, on
    its own, because spinning threads of one pair would slow the next pair down."""
    maps, _ = render_views(args.map_images, 0, *args.view_size)
    queries, _ = render_views(args.queries + args.warmup, -1, *args.view_size)
    cores = torch.get_num_threads()
    counts = sorted({1, cores})
    threads, spinning = [], []
    for method in ("centre", "ga plain"):
        base = method_pipeline("paper", method, maps, args)
        for count in counts:
            threads.append(Pair(method, f"torch {count}t", base, count))
            # torch keeps every core for the pipeline's small torch operations.
            swapped = on_engine(base, "onnx", folder, maps, {"threads": count})
            threads.append(Pair(method, f"onnx {count}t", swapped, cores))
            if ncnn_installed():
                swapped = on_engine(base, "ncnn", folder, maps, {"threads": count})
                threads.append(Pair(method, f"ncnn {count}t", swapped, cores))
        for spin in (False, True):
            swapped = on_engine(base, "onnx", folder, maps, {"spinning": spin})
            spinning.append(Pair(method, f"onnx {cores}t{' spin' if spin else ''}", swapped))
    report = {}
    for name, pairs in (("threads", threads), ("spinning", spinning)):
        found = round_robin(pairs, queries, args.warmup)
        torch.set_num_threads(cores)
        engines = tuple(dict.fromkeys(p.engine for p in pairs))
        reference = f"torch {cores}t" if name == "threads" else engines[0]
        report[name] = summary(found, (reference, *engines))
        print(table(report[name], f"{name}, paper geometry", reference))
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=12)
    parser.add_argument("--warmup", type=int, default=2, help="untimed queries per pair")
    parser.add_argument("--map-images", type=int, default=20)
    parser.add_argument("--batch-size", type=int, default=16, help="query.batch_size")
    parser.add_argument("--geometry", nargs="+", default=["paper", "real_cpu"])
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--engines", nargs="+", default=[*CPU_ENGINES, *GPU_ENGINES])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--input-size", type=int, help="replaces the geometry's (tests)")
    parser.add_argument("--view-size", type=int, nargs=2, default=[640, 480], metavar=("W", "H"))
    parser.add_argument("--width", type=float, default=1.0, help="GoogLeNet's width (tests)")
    parser.add_argument("--threads-study", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/engine_cost.json"))
    args = parser.parse_args()
    report: dict = {
        "views": args.view_size,
        "queries": args.queries,
        "warmup": args.warmup,
        "map_images": args.map_images,
        "batch_size": args.batch_size,
        "input_size": args.input_size or SIZES,
        "width": args.width,
        "device": device_name(args.device),
        "machine": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "torch_version": torch.__version__,
        "load_average_1min_before": os.getloadavg()[0],
        "geometries": {},
    }
    try:
        import onnxruntime

        report["onnxruntime_version"] = onnxruntime.__version__
    except ImportError:
        pass
    if ncnn_installed():
        report["ncnn_version"] = importlib.metadata.version("ncnn")
        report["pnnx_version"] = importlib.metadata.version("pnnx")
    timed: Callable[[], float] = time.perf_counter
    started = timed()
    with tempfile.TemporaryDirectory(prefix="relocfw-engine-") as folder:
        for geometry in args.geometry:
            report["geometries"][geometry] = geometry_run(geometry, args, Path(folder))
        if args.threads_study:
            report["threads"] = threads_study(args, Path(folder))
    report["seconds"] = timed() - started
    report["load_average_1min_after"] = os.getloadavg()[0]
    write_json(report, args.out)


if __name__ == "__main__":
    main()
