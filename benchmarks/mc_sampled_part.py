"""What Monte Carlo dropout's sampled layers cost in torch and as an onnxruntime graph.

engine=onnx runs the dropout-free trunk as a graph and the layers each sample reruns
(kendall: a dropout on the trunk's maps, the pool, the descriptor layer, the head's
dropout and the regressor) in torch (relocfw.model.onnx_graphs). The alternative the
issue names: export those layers with the dropout masks as inputs. This times both on
the same maps of one window, 40 samples, alternating, medians of --repeats runs; the
graph's time includes drawing its masks, with numpy, or with torch's bernoulli_ as the
torch path's dropout draws them (the only way to keep its samples); and the time of
drawing torch's masks alone.

    .venv/bin/python benchmarks/mc_sampled_part.py --repeats 15
"""

from __future__ import annotations

import argparse
import io
import time
import warnings
from pathlib import Path

import numpy as np
import onnxruntime
import torch
from common import write_json  # benchmarks/, the script's own folder
from torch import nn

from relocfw.model.dropout_backbone import pool
from relocfw.model.onnx_engine import available_cores
from relocfw.plugins.posenet import PoseNet


class SampledLayers(nn.Module):
    """The kendall variant's per-sample layers, masks given: [S] poses."""

    def __init__(self, network: PoseNet) -> None:
        super().__init__()
        self.head = network.head

    def forward(
        self, maps: torch.Tensor, on_maps: torch.Tensor, on_descriptor: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        descriptors = self.head.describe(pool(maps * on_maps))
        return self.head.regressor(descriptors * on_descriptor)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--input-size", type=int, default=224)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/mc_sampled_part.json"))
    args = parser.parse_args()
    torch.manual_seed(0)
    network = PoseNet(args.input_size, dropout_variant="kendall", mc_samples=args.samples).eval()
    with torch.inference_mode():
        maps = network.feature_maps(torch.rand(1, 3, args.input_size, args.input_size))
    samples, rate = args.samples, network.dropout_rate
    repeated = maps.expand(samples, -1, -1, -1).contiguous()
    keep = 1.0 / (1.0 - rate)
    graph = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            SampledLayers(network).eval(),
            (repeated, torch.ones_like(repeated), torch.ones(samples, network.feature_dim)),
            graph,
            dynamo=False,
            input_names=["maps", "on_maps", "on_descriptor"],
            output_names=["positions", "quaternions"],
            opset_version=17,
        )
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = available_cores()
    session = onnxruntime.InferenceSession(
        graph.getvalue(), options, providers=["CPUExecutionProvider"]
    )
    rng = np.random.default_rng(0)

    def in_torch() -> None:
        with torch.inference_mode():
            network.head.sampled_above(
                maps,
                lambda m: pool(network.drop(m)),
                pool(maps),
                network.to_world_positions,
                samples,
            )

    def as_graph() -> None:
        on_maps = (rng.random(repeated.shape) >= rate).astype(np.float32) * keep
        on_descriptor = (rng.random((samples, network.feature_dim)) >= rate).astype(np.float32)
        session.run(
            None,
            {"maps": repeated.numpy(), "on_maps": on_maps, "on_descriptor": on_descriptor * keep},
        )

    generator = torch.Generator().manual_seed(0)

    def torch_masks() -> tuple[torch.Tensor, torch.Tensor]:
        # As nn.functional.dropout draws them: Bernoulli(1 - rate) from a seeded torch
        # stream, the only way the samples stay those of the torch path.
        on_maps = torch.empty(repeated.shape).bernoulli_(1 - rate, generator=generator)
        on_descriptor = torch.empty(samples, network.feature_dim)
        return on_maps, on_descriptor.bernoulli_(1 - rate, generator=generator)

    def as_graph_torch_masks() -> None:
        on_maps, on_descriptor = torch_masks()
        session.run(
            None,
            {
                "maps": repeated.numpy(),
                "on_maps": (on_maps * keep).numpy(),
                "on_descriptor": (on_descriptor * keep).numpy(),
            },
        )

    ways = {
        "torch": in_torch,
        "onnxruntime graph, masks as inputs": as_graph,
        "onnxruntime graph, masks drawn by torch": as_graph_torch_masks,
        "drawing torch's masks only": torch_masks,
    }
    for way in ways.values():
        way()
        way()
    times = {name: [] for name in ways}
    for _ in range(args.repeats):
        for name, way in ways.items():
            started = time.perf_counter()
            way()
            times[name].append(time.perf_counter() - started)
    rows = [{"way": name, "ms": 1000 * float(np.median(t))} for name, t in times.items()]
    for row in rows:
        print(f"{row['way']:<42} {row['ms']:7.2f} ms for {samples} samples of one window")
    report = {
        "input_size": args.input_size,
        "samples": samples,
        "repeats": args.repeats,
        "threads": available_cores(),
        "torch_version": torch.__version__,
        "onnxruntime_version": onnxruntime.__version__,
        "rows": rows,
    }
    write_json(report, args.out)


if __name__ == "__main__":
    main()
