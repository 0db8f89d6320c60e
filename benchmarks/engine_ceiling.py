"""How close each inference engine runs the paper's network to the CPU's arithmetic peak.

Issue 23 asks for the paper's method (the GA, about 22 plain network passes per query)
at least 2x faster than torch. This script measures, on the same machine:

- how much of a plain GA query on onnxruntime is the network: the time inside
  onnxruntime's `run` over the whole query (--ga-queries rendered 640 x 480 views).
  When that is nearly all, the question is how many multiply-adds per second an
  engine gets out of the CPU;
- the CPU's practical peak: the best of torch's and numpy's square matrix products
  in float32 (and torch's in bfloat16, where the CPU has it), before and after the
  engines run;
- GoogLeNet PoseNet at 224 px on a batch of --batch crops (a GA generation is 1-10
  new crops) on each engine, in one round robin: torch float32 in channels-last (what
  relocfw's torch path runs), onnxruntime float32 (relocfw's default engine), the
  same with the batch split over two one-thread sessions, OpenVINO float32 (if
  installed), torch bfloat16 autocast, torch with NNPACK's fast algorithms (Winograd
  or FFT, its choice) for the 3 x 3 convolutions (with its largest difference from
  torch's descriptors), onnxruntime int8 static (onnx.int8=static) and, where the CPU
  has VNNI, with 8-bit weights (onnx.int8=static_8bit); ncnn float32 (engine=ncnn,
  Winograd kernels for the 3 x 3 convolutions; with its largest descriptor difference
  from torch), where relocfw[ncnn] is installed;
- per engine: ms per batch, multiply-adds per second, the share of the float32 peak
  and the speed-up over torch; and what a 2x speed-up over torch would need.

Weights are freshly initialised (time does not depend on them).

    .venv/bin/python benchmarks/engine_ceiling.py --repeats 15
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import importlib.metadata
import os
import platform
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from common import device_name, render_views, write_json  # benchmarks/, the script's folder
from engine_cost import method_pipeline, network

from relocfw.core.multiply_adds import multiply_adds_by_layer
from relocfw.model.cpu_flags import cpu_flags, int8_saturation_reason
from relocfw.model.ncnn_engine import ncnn_engine, ncnn_installed
from relocfw.model.onnx_engine import (
    EngineOptions,
    EngineUnavailableError,
    graph_path,
    onnx_engine,
)
from relocfw.model.onnx_graphs import KINDS

WANTED_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_bf16")


def vector_flags() -> list[str]:
    """The CPU's vector extensions that matter here (Linux; [] elsewhere)."""
    flags = cpu_flags() or set()
    return [flag for flag in WANTED_FLAGS if flag in flags]


def has_bfloat16() -> bool:
    """Native bfloat16 arithmetic; elsewhere torch emulates it, slower than float32."""
    return bool({"avx512_bf16", "amx_bf16"} & set(vector_flags()))


def matmul_peak(dtype: torch.dtype, size: int, repeats: int) -> float:
    """Multiply-adds per second of a size x size matrix product, the best of `repeats`
    runs and, in float32, of torch's and numpy's BLAS (on AMD CPUs one of them may
    not pick its widest kernels)."""
    generator = torch.Generator().manual_seed(0)
    a = torch.randn(size, size, generator=generator).to(dtype)
    b = torch.randn(size, size, generator=generator).to(dtype)
    products: list[Callable] = [lambda: a @ b]
    if dtype == torch.float32:
        a_numpy, b_numpy = a.numpy(), b.numpy()
        products.append(lambda: a_numpy @ b_numpy)
    best = float("inf")
    with torch.inference_mode():
        for product in products:
            product()
            for _ in range(repeats):
                started = time.perf_counter()
                product()
                best = min(best, time.perf_counter() - started)
    return size**3 / best


class NnpackConvolution(torch.nn.Module):
    """A stride-1 convolution run by NNPACK (bundled with torch), which picks a fast
    algorithm (Winograd or FFT) itself: the one fast-convolution library at hand."""

    def __init__(self, conv: torch.nn.Conv2d) -> None:
        super().__init__()
        self.weight = conv.weight.detach().contiguous()
        bias = conv.bias if conv.bias is not None else torch.zeros(conv.out_channels)
        self.bias = bias.detach().contiguous()
        self.padding = list(conv.padding)

    def forward(self, maps: torch.Tensor) -> torch.Tensor:
        return torch._nnpack_spatial_convolution(
            maps.contiguous(), self.weight, self.bias, self.padding, [1, 1]
        )


def with_nnpack_3x3(net: torch.nn.Module) -> torch.nn.Module:
    """`net` (changed in place) with every stride-1 3 x 3 convolution run by NNPACK."""
    for parent in list(net.modules()):
        for name, child in parent.named_children():
            square = isinstance(child, torch.nn.Conv2d) and child.kernel_size == (3, 3)
            if square and child.stride == (1, 1) and child.groups == 1:
                setattr(parent, name, NnpackConvolution(child))
    return net


def engines(
    net: torch.nn.Module, batch: torch.Tensor, folder: Path, calibration: list, facts: dict
) -> dict[str, Callable]:
    """One call per engine, each running `net` on `batch`. Every onnxruntime row
    calls its session directly with the same numpy batch and thread count, so rows
    differ only in the graph and how it is run. What is learnt on the way goes into
    `facts`."""
    cores = torch.get_num_threads()
    nnpack = with_nnpack_3x3(copy.deepcopy(net)) if torch.backends.nnpack.is_available() else None
    # relocfw's torch path (relocfw.core.scorer) runs weights and inputs channels-last.
    net.to(memory_format=torch.channels_last)
    channels_last = batch.contiguous(memory_format=torch.channels_last)
    found: dict[str, Callable] = {"torch float32": lambda: net(channels_last)}
    if has_bfloat16():

        def bfloat16() -> object:
            with torch.autocast("cpu", dtype=torch.bfloat16):
                return net(channels_last)

        found["torch bfloat16 autocast"] = bfloat16
    if nnpack is not None:
        found["torch float32, NNPACK for the 3 x 3 convolutions"] = lambda: nnpack(batch)
        with torch.inference_mode():
            reference, fast = net(channels_last).features, nnpack(batch).features
        difference = (fast - reference).abs().max() / reference.abs().max()
        facts["nnpack_largest_relative_descriptor_difference"] = float(difference)
    images = batch.numpy()
    owner = folder / "net.pt"

    def full_session(options: EngineOptions, calibration: list | None = None):  # noqa: ANN202
        return onnx_engine(net, owner, options, calibration).sessions["full"]

    whole = full_session(EngineOptions(threads=cores))
    name = whole.get_inputs()[0].name
    found["onnxruntime float32"] = lambda: whole.run(None, {name: images})
    if len(images) >= 2:
        halves = [full_session(EngineOptions(threads=1)) for _ in range(2)]
        parts = np.array_split(images, 2)
        pool = ThreadPoolExecutor(max_workers=1)

        def split_batch() -> None:
            # Two one-thread sessions on half the batch each: parallel over images
            # instead of inside each convolution (onnxruntime releases the GIL).
            other = pool.submit(halves[1].run, None, {name: parts[1]})
            halves[0].run(None, {name: parts[0]})
            other.result()  # raises what the other thread raised

        found["onnxruntime float32, 2 x 1 thread"] = split_batch
    try:
        import openvino

        compiled = openvino.Core().compile_model(
            str(graph_path(owner, KINDS["full"])),
            "CPU",
            {"INFERENCE_NUM_THREADS": cores, "INFERENCE_PRECISION_HINT": "f32"},
        )
        request = compiled.create_infer_request()
        found["openvino float32"] = lambda: request.infer({0: images})
    except ImportError:
        print("openvino is not installed: its row is left out")
    except Exception as error:  # openvino's own types: a graph it cannot compile
        print(f"openvino cannot run the graph ({type(error).__name__}: {error}): row left out")
    if not ncnn_installed():
        print('ncnn or pnnx is not installed ("relocfw[ncnn]"): its row is left out')
    else:
        try:
            on_ncnn = ncnn_engine(net, owner, EngineOptions(threads=cores)).sessions["full"]
        except EngineUnavailableError as error:
            print(f"ncnn cannot run the network ({error}): its row is left out")
        else:
            found["ncnn float32 (Winograd)"] = lambda: on_ncnn.run(None, {name: images})
            with torch.inference_mode():
                reference = net(channels_last).features.numpy()
            fast = on_ncnn.run(["features"], {name: images})[0]
            difference = np.abs(fast - reference).max() / np.abs(reference).max()
            facts["ncnn_largest_relative_descriptor_difference"] = float(difference)
    modes = {"static": "onnxruntime int8 static"}
    if int8_saturation_reason() is None:  # VNNI: 8-bit weights multiply exactly
        modes["static_8bit"] = "onnxruntime int8 static, 8-bit weights"
    for mode, label in modes.items():
        session = full_session(EngineOptions(threads=cores, int8=mode), calibration)
        found[label] = lambda session=session: session.run(None, {name: images})
    return found


def library_versions() -> dict[str, str]:
    """The engines' versions, for the report (absent: not installed)."""
    versions = {}
    for package in ("onnxruntime", "openvino", "ncnn", "pnnx", "numpy"):
        with contextlib.suppress(importlib.metadata.PackageNotFoundError):
            versions[package] = importlib.metadata.version(package)
    return versions


def work_by_kernel(by_layer: dict[torch.nn.Module, int]) -> dict[str, float]:
    """Each convolution kernel size's share of the multiply-adds ("linear" for fully
    connected layers): what a fast-convolution algorithm (Winograd for 3 x 3) could
    cut is bounded by its kernels' share."""
    work: dict[str, int] = {}
    for layer, count in by_layer.items():
        size = getattr(layer, "kernel_size", None)
        key = "linear" if size is None else "x".join(map(str, size))
        if getattr(layer, "stride", (1,))[0] != 1:
            key += " strided"
        work[key] = work.get(key, 0) + count
    total = sum(work.values())
    return {key: value / total for key, value in sorted(work.items(), key=lambda kv: -kv[1])}


class TimedSession:
    """An onnxruntime session that adds the time of each `run` to `spent`."""

    def __init__(self, session, spent: list[float]) -> None:  # noqa: ANN001
        self.session, self.spent = session, spent

    def run(self, *args, **kwargs):  # noqa: ANN002, ANN003, ANN201
        started = time.perf_counter()
        try:
            return self.session.run(*args, **kwargs)
        finally:
            self.spent.append(time.perf_counter() - started)


def network_share_of_ga(args: argparse.Namespace, folder: Path) -> dict:
    """How much of a plain GA query on onnxruntime is the network's passes: the time
    inside onnxruntime's `run` over the whole `localize`, at the paper's geometry."""
    shape = argparse.Namespace(
        input_size=args.input_size, width=args.width, batch_size=16, device="cpu"
    )
    maps, _ = render_views(20, 0)
    queries, _ = render_views(args.ga_queries + 1, -1)
    relocalizer = method_pipeline("paper", "ga plain", maps, shape)
    engine = onnx_engine(relocalizer.backbone, folder / "ga.pt", EngineOptions())
    spent: list[float] = []
    engine.sessions = {kind: TimedSession(s, spent) for kind, s in engine.sessions.items()}
    relocalizer = relocalizer.replace(backbone=engine)
    relocalizer.localize(queries[0])  # warm-up
    spent.clear()
    started = time.perf_counter()
    answers = [relocalizer.localize(query) for query in queries[1:]]
    total = time.perf_counter() - started
    return {
        "queries": args.ga_queries,
        "ms_per_query": 1000 * total / args.ga_queries,
        "network_ms_per_query": 1000 * sum(spent) / args.ga_queries,
        "network_share": sum(spent) / total,
        # onnxruntime runs (one per GA generation) and the crops they scored
        "runs_per_query": len(spent) / args.ga_queries,
        "crops_per_query": float(np.mean([a.network_passes for a in answers])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=6, help="crops per pass")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--matmul-size", type=int, default=3072)
    parser.add_argument("--ga-queries", type=int, default=8, help="for the network's share")
    parser.add_argument("--input-size", type=int, default=224, help="smaller for tests")
    parser.add_argument("--width", type=float, default=1.0, help="GoogLeNet's width (tests)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/engine_ceiling.json"))
    args = parser.parse_args()
    started = time.perf_counter()
    generator = torch.Generator().manual_seed(0)
    size = args.input_size
    batch = torch.rand(args.batch, 3, size, size, generator=generator)
    peak = {"float32": matmul_peak(torch.float32, args.matmul_size, 5)}
    if has_bfloat16():
        peak["bfloat16"] = matmul_peak(torch.bfloat16, args.matmul_size, 5)
    net = network("paper", size=size, width=args.width)
    with torch.inference_mode():
        by_layer = multiply_adds_by_layer(net, lambda: net(batch))
    work = sum(by_layer.values())
    kernels = work_by_kernel(by_layer)
    with tempfile.TemporaryDirectory(prefix="relocfw-ceiling-") as folder:
        share = network_share_of_ga(args, Path(folder))
        facts: dict = {}
        calls = engines(net, batch, Path(folder), render_views(20, 0, 160, 120)[0], facts)
        times: dict[str, list[float]] = {name: [] for name in calls}
        with torch.inference_mode():
            for call in calls.values():
                call()
            for repeat in range(args.repeats):
                order = list(calls)
                shift = repeat % len(order)
                for name in order[shift:] + order[:shift]:
                    begun = time.perf_counter()
                    calls[name]()
                    times[name].append(time.perf_counter() - begun)
    # Measured again after the engines, in case the clock moved while they ran.
    for kind, dtype in (("float32", torch.float32), ("bfloat16", torch.bfloat16)):
        if kind in peak:
            peak[kind] = max(peak[kind], matmul_peak(dtype, args.matmul_size, 5))
    torch_ms = 1000 * float(np.median(times["torch float32"]))
    rows = []
    for name, spent in times.items():
        ms = 1000 * float(np.median(spent))
        rate = work / (ms / 1000)
        rows.append(
            {
                "engine": name,
                "ms_per_batch": ms,
                "giga_multiply_adds_per_s": rate / 1e9,
                "share_of_float32_peak": rate / peak["float32"],
                "speedup_over_torch": torch_ms / ms,
            }
        )
    needed = 2 * work / (torch_ms / 1000)
    report = {
        "batch": args.batch,
        "repeats": args.repeats,
        "network": f"GoogLeNet PoseNet, {size} px, width {args.width}",
        "multiply_adds_per_batch": work,
        "share_of_multiply_adds_by_kernel": kernels,
        "peak_giga_multiply_adds_per_s": {k: v / 1e9 for k, v in peak.items()},
        "plain_ga_on_onnxruntime": share,
        **facts,
        "two_x_torch_needs_giga_multiply_adds_per_s": needed / 1e9,
        "two_x_torch_needs_share_of_float32_peak": needed / peak["float32"],
        "rows": rows,
        "device": device_name("cpu"),
        "machine": platform.processor() or platform.machine(),
        "cpu_flags": vector_flags(),
        "cores": os.cpu_count(),
        "torch_version": torch.__version__,
        "library_versions": library_versions(),
        "load_average_1min": os.getloadavg()[0],
        "seconds": time.perf_counter() - started,
    }
    print(
        f"plain GA on onnxruntime: {share['ms_per_query']:.1f} ms/query, of which the "
        f"network {share['network_ms_per_query']:.1f} ms ({100 * share['network_share']:.1f}%), "
        f"{share['runs_per_query']:.1f} runs of {share['crops_per_query']:.1f} crops in all"
    )
    print(f"CPU flags: {' '.join(vector_flags())}; torch threads {torch.get_num_threads()}")
    for kind, value in peak.items():
        size = args.matmul_size
        print(f"peak {kind} (matrix product {size}): {value / 1e9:.1f} G multiply-adds/s")
    print(f"{report['network']}, batch {args.batch}: {work / 1e9:.2f} G multiply-adds")
    shares = ", ".join(f"{kernel} {100 * share:.1f}%" for kernel, share in kernels.items())
    print(f"multiply-adds by kernel: {shares}")
    print("| engine | ms per batch | G multiply-adds/s | share of float32 peak | x torch |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['engine']} | {r['ms_per_batch']:.1f} | {r['giga_multiply_adds_per_s']:.1f} | "
            f"{100 * r['share_of_float32_peak']:.0f}% | {r['speedup_over_torch']:.2f}x |"
        )
    print(
        f"2x torch needs {needed / 1e9:.1f} G multiply-adds/s: "
        f"{100 * needed / peak['float32']:.0f}% of the float32 peak"
    )
    write_json(report, args.out)


if __name__ == "__main__":
    main()
